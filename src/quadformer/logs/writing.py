"""What the DataFlash and ULog writers share: the vehicle's clock, GPS time, the streams in
the autopilots' frames, and what a written log says about itself.

A writer takes a ``FlightLog`` (SI units, world ENU, body FLU, times in seconds) and is the
inverse of its format's reader: ``read_log`` of the file gives back the streams, within the
format's quantisation. The conversions are the readers' own, applied backwards (each frame
change is a 180 degree rotation, its own inverse; ``frames``):

* times: the vehicle's clock, microseconds since boot, is ``boot_t0 + t`` (a log whose
  ``boot_t0`` is not known is written as if the vehicle booted ``BOOT_S`` before its first
  sample: PX4 reads a timestamp of 0 as never set);
* vectors: ENU -> NED, FLU -> FRD; attitudes: body FLU -> world ENU becomes body FRD -> world
  NED, as (w, x, y, z) quaternions or Z-Y-X Euler angles in degrees;
* positions: geodetic about ``FlightLog.origin`` (WGS84, through ``frames``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import pandas as pd

from quadformer.geometry import frames
from quadformer.logs.flightlog import FlightLog

__all__ = ["BOOT_S", "GATE", "LogHeader", "clock_us", "enu_to_ned", "euler_ned_deg", "first_t", "gps_reports",
           "gps_utc", "gps_week_ms", "quat_ned_wxyz", "start_us", "values"]

BOOT_S = 1.0             # s, the vehicle's clock at the first sample when the log does not say
GATE = 5.0               # innovation gate (standard deviations) of the autopilots' test ratios
_GPS_EPOCH = 315_964_800.0   # s, 1980-01-06 00:00 UTC in UNIX time
_LEAP_S = 18.0               # s, GPS time minus UTC since 2017
_WEEK_S = 7 * 86_400.0


@dataclass(frozen=True)
class LogHeader:
    """What a written log says about itself besides its streams.

    text: a status text at the start (DataFlash MSG, ULog logged message), naming what
    recorded the flight; utc0: UNIX time (s) at t = 0, giving the fixes their GPS week and
    time (None: not known, written as 0); airborne: armed and in flight from the first sample
    (ArduPilot ARM with the EV events armed and not landed; PX4 vehicle_status armed and
    vehicle_land_detected not landed); params: parameters written beside the format's own
    defaults (name -> value); gps_delay_s: the receiver latency the autopilot is set to
    compensate (s; PX4 ``EKF2_GPS_DELAY``, ArduPilot ``GPS_DELAY_MS``, both in ms); gps_epochs:
    (stamps, epochs), the time each GPS report was measured at (s, the log's clock) where it is
    not its stamp (a receiver's latency, a late read; ``logs.conditions``), so that the
    receiver's time of week written with each fix stays its measurement's (None: every report
    measured at its stamp)."""
    text: str = "quadformer simulator: a simulated flight, not autopilot firmware"
    utc0: float | None = None
    airborne: bool = True
    params: Mapping[str, float] = field(default_factory=dict)
    gps_delay_s: float = 0.0
    gps_epochs: tuple[np.ndarray, np.ndarray] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if self.utc0 is not None and not (isinstance(self.utc0, (int, float)) and math.isfinite(self.utc0)
                                          and self.utc0 >= _GPS_EPOCH):
            raise ValueError(f"utc0 must be a UNIX time after the GPS epoch (1980-01-06), got {self.utc0!r}")
        if not (isinstance(self.gps_delay_s, (int, float)) and math.isfinite(self.gps_delay_s)
                and self.gps_delay_s >= 0):
            raise ValueError(f"gps_delay_s must be a non-negative number of seconds, got {self.gps_delay_s!r}")
        if self.gps_epochs is not None:
            stamps, epochs = (np.asarray(a, dtype=float) for a in self.gps_epochs)
            if stamps.ndim != 1 or stamps.shape != epochs.shape or np.any(np.diff(stamps) <= 0):
                raise ValueError("gps_epochs must be (stamps, epochs): two 1-D arrays of the same length, the "
                                 "stamps strictly increasing")
            object.__setattr__(self, "gps_epochs", (stamps, epochs))


def first_t(log: FlightLog) -> float:
    """The earliest time of any stream of ``log`` (s); ValueError for a log without samples."""
    firsts = [float(df["t"].iloc[0]) for df in log.streams.values()]
    if not firsts:
        raise ValueError(f"{log.path}: the FlightLog holds no stream to write")
    return min(firsts)


def _boot_t0(log: FlightLog) -> float:
    return log.boot_t0 if math.isfinite(log.boot_t0) else BOOT_S - first_t(log)


def clock_us(log: FlightLog, t) -> np.ndarray:
    """The vehicle's clock (integer microseconds since boot) at times ``t`` of ``log``."""
    us = np.round((_boot_t0(log) + np.asarray(t, dtype=float)) * 1e6)
    if len(us) and us.min() <= 0:
        raise ValueError(f"{log.path}: boot_t0 {log.boot_t0} puts samples at or before the vehicle's boot "
                         "(times since boot must be positive)")
    return us.astype(np.int64)


def start_us(log: FlightLog) -> int:
    """The vehicle's clock at the log's first sample (microseconds since boot)."""
    return int(clock_us(log, [first_t(log)])[0])


def gps_reports(log: FlightLog) -> pd.DataFrame | None:
    """What the receiver reported, one row per GPS message to write: the ``gps`` stream's fixes
    and the ``receiver`` stream's reports without a fix (a lost lock), in time order, with the
    ``gps`` columns and ``noise``. At a fix's time its own values stand and the receiver's report
    adds only its noise; a report without a fix holds the last fix's position and velocity (the
    first fix's before any), as a receiver repeats its last solution. None without a gps stream."""
    gps = log.gps
    if gps is None:
        return None
    out = gps.assign(noise=np.nan)
    rec = log.receiver
    if rec is None or not len(rec):
        return out
    t, rt = gps["t"].to_numpy(), rec["t"].to_numpy()
    j = np.clip(np.searchsorted(t, rt), 0, len(t) - 1)
    k = np.clip(np.searchsorted(t, rt, side="right") - 1, 0, len(t) - 1)
    same = np.abs(t[j] - rt) <= 1e-9
    noise = out["noise"].to_numpy(dtype=float, copy=True)
    noise[j[same]] = rec["noise"].to_numpy()[same]
    out["noise"] = noise
    if same.all():
        return out
    extra = gps.iloc[k[~same]].reset_index(drop=True)         # the last solution, repeated
    extra["t"] = rt[~same]
    for c in ("fix_type", "satellites", "eph", "epv", "speed_acc", "jamming", "spoofing", "noise"):
        extra[c] = rec[c].to_numpy()[~same]
    return pd.concat([out, extra], ignore_index=True).sort_values("t", kind="stable").reset_index(drop=True)


def gps_utc(header: LogHeader, t: np.ndarray) -> np.ndarray | None:
    """The UNIX time (s) at which each GPS report stamped at ``t`` (s, the log's clock) was
    measured: ``utc0`` + its epoch (``header.gps_epochs``; the stamp itself without them). None
    where ``utc0`` is not known; ValueError for a report stamped at no time of ``gps_epochs``."""
    if header.utc0 is None:
        return None
    t = np.asarray(t, dtype=float)
    if header.gps_epochs is None:
        return header.utc0 + t
    stamps, epochs = header.gps_epochs
    j = np.clip(np.searchsorted(stamps, t), 0, max(len(stamps) - 1, 0))
    if not len(stamps) or np.any(np.abs(stamps[j] - t) > 1e-9):
        raise ValueError("a GPS report is stamped at a time that LogHeader.gps_epochs does not hold; give the "
                         "epoch of every report written")
    return header.utc0 + epochs[j]


def gps_week_ms(utc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GPS week and milliseconds of the week of UNIX times ``utc`` (s)."""
    gps = np.asarray(utc, dtype=float) - _GPS_EPOCH + _LEAP_S
    week = np.floor(gps / _WEEK_S)
    return week.astype(np.int64), np.round((gps - week * _WEEK_S) * 1e3).astype(np.int64)


def values(df: pd.DataFrame, *columns: str) -> np.ndarray:
    """Columns of a stream as a float (n, k) array."""
    return df[list(columns)].to_numpy(dtype=np.float64)


def enu_to_ned(df: pd.DataFrame, *columns: str) -> np.ndarray:
    """Three ENU (or FLU) columns as NED (or FRD) (n, 3); the same map both ways."""
    return frames.ned_to_enu(values(df, *columns))


def quat_ned_wxyz(df: pd.DataFrame) -> np.ndarray:
    """A stream's attitude ``qx..qw`` (body FLU -> world ENU) as (w, x, y, z), body FRD -> world NED."""
    q = frames.quat_ned_frd_to_enu_flu(values(df, "qx", "qy", "qz", "qw"))
    return frames.xyzw_to_wxyz(q)


def euler_ned_deg(q_wxyz: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (deg; Z-Y-X, body FRD -> world NED) of (w, x, y, z) quaternions, (n, 3)."""
    return np.degrees(np.column_stack(frames.quat_to_euler(frames.wxyz_to_xyzw(q_wxyz))))

