"""ArduPilot DataFlash (.bin) writer: ``write_dataflash(log, path)``, one flight through pymavlink's
format machinery.

Messages in ArduCopter 4.x's layout (their formats from pymavlink's ``DFReader.DFFormat``, so
the scaled fields carry ArduPilot's multipliers: centidegrees for ``c``/``C``, 1e-7 degrees for
``L``, centimetres for ``e``), at each stream's own times, in time order:

* header: FMT for every message type written; PARM (``GPS_DELAY_MS``: ``LogHeader.gps_delay_s``
  in ms, 0 by default; the EKF3 gates, GPS as EKF3's position, height and velocity source
  (``EK3_SRC1_*`` 3), ``LOG_DISARMED`` 0 and ``LogHeader.params``); MSG (``LogHeader.text`` and the frame);
  ORGN type 0 (the EKF origin: ``FlightLog.origin``); with ``LogHeader.airborne``, ARM (armed),
  EV 10 (armed), EV 28 (not landed: the flight is under way at the first sample) and MODE
  AUTO;
* imu -> IMU instance 0 (``GyrX..Z`` rad/s, ``AccX..Z`` m/s^2, FRD);
* gps -> GPS (``Status`` = fix_type, 3 when not logged; ``Lat``/``Lng``, ``Alt`` AMSL in cm;
  ``Spd``, ``GCrs``, ``VZ`` down; ``GWk``/``GMS``, the GPS week and time of the fix's
  measurement: ``LogHeader.utc0`` + its epoch, ``writing.gps_utc``) and GPA of the same
  ``TimeUS`` (``HAcc`` eph, ``VAcc`` epv, ``SAcc`` speed accuracy, cm; ``VV`` 1 where vz is
  known); NSats as logged (0 when not), dilution not modelled (HDop/VDop 1); with a receiver
  stream, its reports without a fix too (``writing.gps_reports``: the last fix repeated, its
  Status below 2); the receiver's noise has no field in these messages;
* baro -> BARO instance 0 (``Alt``: height above the origin, as ArduPilot logs altitude above
  its ground calibration; ``Press`` and ``Temp`` from the standard atmosphere at origin
  altitude + Alt);
* mag -> MAG instance 0 (``MagX..Z`` milligauss FRD, integers);
* attitude -> ATT (``Roll``, ``Pitch``, ``Yaw`` centidegrees, NED; the desired angles 0);
* estimate -> XKF1 core 0 (``PN/PE/PD`` about ORGN, ``VN/VE/VD``; its Euler angles from the
  attitude stream interpolated to its times); resets are not written (ArduPilot logs a reset's
  offset, which a FlightLog does not hold);
* innovations -> XKF3 core 0 (``IPN/IPE/IPD``, ``IVN/IVE/IVD``: predicted minus measured,
  NED, centimetres; values beyond the int16 range are clipped to +-327.67) and XKF4 core 0
  (``SV``, ``SP``, ``SH``: the square roots of EKF3's test ratios, ``ardupilot_ratios``: the
  summed squared innovations of the velocity (N, E, D; N, E where the vertical one is not
  known), the horizontal position and the height over their summed variances and the squared
  5-sigma gate; where the stream has no variances, its own ratio columns; ``PI`` 0: one core);
  variances are not in EKF3's messages (a reader recovers them from the ratios);
* odometry -> VISP (``PX/PY/PZ`` NED, ``Roll/Pitch/Yaw`` deg) and VISV (``VX/VY/VZ`` NED);
* truth -> SIM (``Lat``/``Lng``/``Alt``, ``Roll/Pitch/Yaw``, ``Q1..Q4`` = w, x, y, z body FRD ->
  NED) and SIM2 (``PN/PE/PD`` about the origin, ``VN/VE/VD``; airspeed not modelled, NaN).

A NaN in an integer field is written as 0. The file is written atomically.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
from pymavlink import DFReader

from quadformer.geometry import frames
from quadformer.io import atomic_write_bytes
from quadformer.logs._series import quat_interp
from quadformer.logs.ardupilot_ratios import innovation_test_ratios
from quadformer.logs.flightlog import FlightLog
from quadformer.logs.writing import (GATE, LogHeader, clock_us, enu_to_ned, euler_ned_deg, gps_reports,
                                     gps_utc, gps_week_ms, quat_ned_wxyz, start_us, values)

__all__ = ["FORMATS", "write_dataflash"]

#: name -> (format characters, columns): ArduCopter 4.x's layouts of the messages written
FORMATS: dict[str, tuple[str, str]] = {
    "PARM": ("QNf", "TimeUS,Name,Value"),
    "MSG": ("QZ", "TimeUS,Message"),
    "ORGN": ("QBLLe", "TimeUS,Type,Lat,Lng,Alt"),
    "ARM": ("QBIBB", "TimeUS,ArmState,ArmChecks,Forced,Method"),
    "EV": ("QB", "TimeUS,Id"),
    "MODE": ("QMBB", "TimeUS,Mode,ModeNum,Rsn"),
    "IMU": ("QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
    "GPS": ("QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    "GPA": ("QBCCCCfBIH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta"),
    "BARO": ("QBffcfIffB", "TimeUS,I,Alt,Press,Temp,CRt,SMS,Offset,GndTemp,Health"),
    "MAG": ("QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    "ATT": ("QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),
    "XKF1": ("QBccCfffffffccce", "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD,dPD,PN,PE,PD,GX,GY,GZ,OH"),
    "XKF3": ("QBcccccchhhccff", "TimeUS,C,IVN,IVE,IVD,IPN,IPE,IPD,IMX,IMY,IMZ,IYAW,IVT,RErr,ErSc"),
    "XKF4": ("QBcccccfffHBIHb", "TimeUS,C,SV,SP,SH,SM,SVT,errRP,OFN,OFE,FS,TS,SS,GPS,PI"),
    "VISP": ("QQIffffffffBB", "TimeUS,RTimeUS,CTimeMS,PX,PY,PZ,Roll,Pitch,Yaw,PErr,AErr,Rst,Ign"),
    "VISV": ("QQIffffBB", "TimeUS,RTimeUS,CTimeMS,VX,VY,VZ,VErr,Rst,Ign"),
    "SIM": ("QccCfLLffff", "TimeUS,Roll,Pitch,Yaw,Alt,Lat,Lng,Q1,Q2,Q3,Q4"),
    "SIM2": ("Qdddffff", "TimeUS,PN,PE,PD,VN,VE,VD,As"),
}
#: parameters every written log carries: the receiver latency (0; ``LogHeader.gps_delay_s`` sets it),
#: EKF3's default innovation gates (the test ratios' scale), GPS the source of horizontal and
#: vertical position and velocity (EK3_SRC1_*: 3, so that XKF3.IPD and XKF4.SH are the GPS's),
#: logging while disarmed off
PARAMS = {"GPS_DELAY_MS": 0.0, "EK3_POS_I_GATE": 100 * GATE, "EK3_VEL_I_GATE": 100 * GATE,
          "EK3_HGT_I_GATE": 100 * GATE, "EK3_SRC1_POSXY": 3.0, "EK3_SRC1_VELXY": 3.0, "EK3_SRC1_POSZ": 3.0,
          "EK3_SRC1_VELZ": 3.0, "AHRS_EKF_TYPE": 3.0, "LOG_DISARMED": 0.0}
FRAME = "QUAD/X"
EV_ARMED, EV_NOT_LANDED = 10, 28      # ArduPilot's LogEvent ids
MODE_AUTO = 3                          # ArduCopter's AUTO
_FMT_TYPE = 0x80
_FMT = DFReader.DFFormat(_FMT_TYPE, "FMT", 89, "BBnNZ", "Type,Length,Name,Format,Columns")
_HEADER = struct.pack("<BB", 0xA3, 0x95)
_P0 = 101_325.0          # Pa, standard sea-level pressure
_T0 = 288.15             # K, standard sea-level temperature
_LAPSE = 0.0065          # K/m, tropospheric lapse rate


class _Messages:
    """DataFlash messages packed by pymavlink's format table, sorted by time when assembled."""

    def __init__(self) -> None:
        self.formats: dict[str, DFReader.DFFormat] = {}
        self.out: list[tuple[int, int, bytes]] = []   # (TimeUS, order written, bytes)

    def fmt(self, name: str) -> DFReader.DFFormat:
        if name not in self.formats:
            chars, columns = FORMATS[name]
            self.formats[name] = DFReader.DFFormat(0x81 + len(self.formats), name, 0, chars, columns)
        return self.formats[name]

    def add(self, name: str, columns: dict[str, np.ndarray | float | int | str]) -> None:
        """Messages ``name``, one per row of the columns (scalars broadcast), in ArduPilot's units
        before scaling: a field with a multiplier (``c``, ``e``, ``L``, ...) is divided by it,
        rounded and clipped to its integer's range."""
        fmt = self.fmt(name)
        n = len(columns["TimeUS"])
        cols = []
        for col, ch, mult in zip(fmt.columns, fmt.msg_fmts, fmt.msg_mults):
            code = DFReader.FORMAT_TO_STRUCT[ch][0]
            v = columns.get(col, 0)
            if code.endswith("s"):                                    # text: one string, or one per row
                texts = v if isinstance(v, list) else [v] * n
                cols.append([x.encode() if isinstance(x, str) else bytes(x) for x in texts])
                continue
            a = np.broadcast_to(np.asarray(v, dtype=np.float64), (n,))
            if mult is not None:
                a = a / mult
            if code in "fd":
                cols.append(a.tolist())
                continue
            info = np.iinfo(np.dtype(code))
            a = np.clip(np.round(np.nan_to_num(a, nan=0.0)), info.min, info.max)
            cols.append([int(x) for x in a])
        pack = struct.Struct(fmt.msg_struct).pack
        head = _HEADER + bytes([fmt.type])
        for row in zip(*cols):
            self.out.append((int(row[0]), len(self.out), head + pack(*row)))

    def assemble(self) -> bytes:
        heads = [_HEADER + bytes([_FMT_TYPE]) + struct.pack(
            _FMT.msg_struct, f.type, struct.calcsize(f.msg_struct) + 3, f.name.encode(), f.format.encode(),
            ",".join(f.columns).encode()) for f in self.formats.values()]
        return b"".join(heads) + b"".join(m for _, _, m in sorted(self.out))


def write_dataflash(log: FlightLog, path: str | Path, header: LogHeader = LogHeader()) -> Path:
    """Write ``log`` as an ArduPilot DataFlash file at ``path`` (see the module docstring);
    ValueError for a log without streams or a local origin."""
    path = Path(path)
    if not all(math.isfinite(v) for v in log.origin):
        raise ValueError(f"{log.path}: the FlightLog has no origin (lat, lon, alt); DataFlash positions are "
                         "geodetic or about the EKF origin")
    out = _Messages()
    t0 = start_us(log)
    _header(out, log, header, t0)
    for write in (_imu, _gps, _baro, _mag, _attitude, _estimate, _innovations, _odometry, _truth):
        write(out, log, header)
    return atomic_write_bytes(path, out.assemble())


def _header(out: _Messages, log: FlightLog, header: LogHeader, t0: int) -> None:
    params = {**PARAMS, "GPS_DELAY_MS": round(1e3 * header.gps_delay_s, 3), **header.params}
    if log.mag is None:
        params["COMPASS_ENABLE"] = 0.0
    out.add("PARM", {"TimeUS": np.full(len(params), t0), "Name": list(params),
                     "Value": np.array(list(params.values()), dtype=float)})
    out.add("MSG", {"TimeUS": np.full(2, t0), "Message": [header.text[:64], f"Frame: {FRAME}"]})
    lat, lon, alt = log.origin
    out.add("ORGN", {"TimeUS": [t0], "Type": 0, "Lat": lat, "Lng": lon, "Alt": alt})
    if header.airborne:
        out.add("ARM", {"TimeUS": [t0], "ArmState": 1})
        out.add("EV", {"TimeUS": [t0, t0], "Id": np.array([EV_ARMED, EV_NOT_LANDED])})
        out.add("MODE", {"TimeUS": [t0], "Mode": MODE_AUTO, "ModeNum": MODE_AUTO})


def _imu(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = log.imu
    if d is None:
        return
    acc, gyr = frames.frd_to_flu(values(d, "ax", "ay", "az")), frames.frd_to_flu(values(d, "gx", "gy", "gz"))
    t = d["t"].to_numpy()
    hz = 1.0 / float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    out.add("IMU", {"TimeUS": clock_us(log, t), "GyrX": gyr[:, 0], "GyrY": gyr[:, 1], "GyrZ": gyr[:, 2],
                    "AccX": acc[:, 0], "AccY": acc[:, 1], "AccZ": acc[:, 2], "T": 25.0, "GH": 1, "AH": 1,
                    "GHz": hz, "AHz": hz})


def _gps(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = gps_reports(log)
    if d is None:
        return
    t = d["t"].to_numpy()
    us = clock_us(log, t)
    utc = gps_utc(header, t)
    week, ms = gps_week_ms(utc) if utc is not None else (0, 0)
    v = values(d, "vx", "vy", "vz")
    fix = np.where(np.isfinite(d["fix_type"]), d["fix_type"], 3.0)
    out.add("GPS", {"TimeUS": us, "Status": fix, "GMS": ms, "GWk": week, "NSats": d["satellites"].to_numpy(),
                    "HDop": 1.0, "Lat": d["lat"].to_numpy(), "Lng": d["lon"].to_numpy(), "Alt": d["alt"].to_numpy(),
                    "Spd": np.hypot(v[:, 0], v[:, 1]), "GCrs": np.degrees(np.arctan2(v[:, 0], v[:, 1])) % 360.0,
                    "VZ": -v[:, 2], "U": 1})
    delta = np.diff(us, prepend=us[0]) / 1e3
    out.add("GPA", {"TimeUS": us, "VDop": 1.0, "HAcc": d["eph"].to_numpy(), "VAcc": d["epv"].to_numpy(),
                    "SAcc": d["speed_acc"].to_numpy(), "VV": np.isfinite(v[:, 2]).astype(float),
                    "SMS": us // 1000, "Delta": delta})


def _baro(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = log.baro
    if d is None:
        return
    us = clock_us(log, d["t"].to_numpy())
    alt = d["alt"].to_numpy(dtype=float)
    temp = _T0 - _LAPSE * (log.origin[2] + alt)                           # K, standard atmosphere
    out.add("BARO", {"TimeUS": us, "Alt": alt, "Press": _P0 * (temp / _T0) ** 5.25588, "Temp": temp - 273.15,
                     "SMS": us // 1000, "GndTemp": _T0 - _LAPSE * log.origin[2] - 273.15, "Health": 1})


def _mag(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = log.mag
    if d is None:
        return
    m = frames.frd_to_flu(values(d, "mx", "my", "mz")) * 1e3          # gauss FLU -> milligauss FRD
    us = clock_us(log, d["t"].to_numpy())
    out.add("MAG", {"TimeUS": us, "MagX": m[:, 0], "MagY": m[:, 1], "MagZ": m[:, 2], "Health": 1,
                    "S": us % (1 << 32)})


def _angles(q_wxyz: np.ndarray) -> dict[str, np.ndarray]:
    rpy = euler_ned_deg(q_wxyz)
    return {"Roll": rpy[:, 0], "Pitch": rpy[:, 1], "Yaw": rpy[:, 2] % 360.0}


def _attitude(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = log.attitude
    if d is None:
        return
    out.add("ATT", {"TimeUS": clock_us(log, d["t"].to_numpy()), **_angles(quat_ned_wxyz(d)), "AEKF": 3})


def _estimate(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = log.estimate
    if d is None:
        return
    t = d["t"].to_numpy()
    p, v = enu_to_ned(d, "x", "y", "z"), enu_to_ned(d, "vx", "vy", "vz")
    angles = {}
    if log.attitude is not None:                                   # the attitude at the estimate's times
        a, ta = log.attitude, log.attitude["t"].to_numpy()
        q = quat_interp(np.clip(t, ta[0], ta[-1]), ta, values(a, "qx", "qy", "qz", "qw"))
        angles = _angles(frames.xyzw_to_wxyz(frames.quat_ned_frd_to_enu_flu(q)))
    out.add("XKF1", {"TimeUS": clock_us(log, t), "C": 0, **angles, "VN": v[:, 0], "VE": v[:, 1], "VD": v[:, 2],
                     "dPD": v[:, 2], "PN": p[:, 0], "PE": p[:, 1], "PD": p[:, 2]})


def _innovations(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = log.innovations
    if d is None:
        return
    us = clock_us(log, d["t"].to_numpy())
    p, v = enu_to_ned(d, "pos_x", "pos_y", "pos_z"), enu_to_ned(d, "vel_x", "vel_y", "vel_z")
    out.add("XKF3", {"TimeUS": us, "C": 0, "IVN": v[:, 0], "IVE": v[:, 1], "IVD": v[:, 2],
                     "IPN": p[:, 0], "IPE": p[:, 1], "IPD": p[:, 2]})
    out.add("XKF4", {"TimeUS": us, "C": 0, **{k: np.sqrt(r) for k, r in _test_ratios(d).items()}, "PI": 0})


def _test_ratios(d) -> dict[str, np.ndarray]:
    """XKF4's ratios (SV, SP, SH before their square roots) of an innovations stream: EKF3's
    definitions (``ardupilot_ratios``) from the innovations and their variances, the vertical
    velocity summed where it is known; where a group's variances are not known, the stream's own
    ratio columns."""
    innov = values(d, "pos_x", "pos_y", "pos_z", "vel_x", "vel_y", "vel_z")
    var = values(d, "var_pos_x", "var_pos_y", "var_pos_z", "var_vel_x", "var_vel_y", "var_vel_z")
    vz = np.isfinite(innov[:, 5]) & np.isfinite(var[:, 5])
    ratios = innovation_test_ratios(innov, var, (GATE, GATE, GATE), np.where(vz, 3, 2))
    return {k: np.where(np.isfinite(ratios[c]), ratios[c], d[c].to_numpy(dtype=float))
            for k, c in (("SV", "ratio_vel"), ("SP", "ratio_pos"), ("SH", "ratio_hgt"))}


def _odometry(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = log.odometry
    if d is None:
        return
    us = clock_us(log, d["t"].to_numpy())
    p, v = enu_to_ned(d, "x", "y", "z"), enu_to_ned(d, "vx", "vy", "vz")
    rpy = euler_ned_deg(quat_ned_wxyz(d))
    out.add("VISP", {"TimeUS": us, "RTimeUS": us, "CTimeMS": us // 1000, "PX": p[:, 0], "PY": p[:, 1],
                     "PZ": p[:, 2], "Roll": rpy[:, 0], "Pitch": rpy[:, 1], "Yaw": rpy[:, 2]})
    out.add("VISV", {"TimeUS": us, "RTimeUS": us, "CTimeMS": us // 1000, "VX": v[:, 0], "VY": v[:, 1],
                     "VZ": v[:, 2]})


def _truth(out: _Messages, log: FlightLog, header: LogHeader) -> None:
    d = log.truth
    if d is None:
        return
    us = clock_us(log, d["t"].to_numpy())
    enu = values(d, "x", "y", "z")
    lla = frames.enu_to_geodetic(enu, log.origin)
    q = quat_ned_wxyz(d)
    ned, v = frames.ned_to_enu(enu), enu_to_ned(d, "vx", "vy", "vz")
    out.add("SIM", {"TimeUS": us, **_angles(q), "Alt": lla[:, 2], "Lat": lla[:, 0], "Lng": lla[:, 1],
                    "Q1": q[:, 0], "Q2": q[:, 1], "Q3": q[:, 2], "Q4": q[:, 3]})
    out.add("SIM2", {"TimeUS": us, "PN": ned[:, 0], "PE": ned[:, 1], "PD": ned[:, 2], "VN": v[:, 0],
                     "VE": v[:, 1], "VD": v[:, 2], "As": np.nan})
