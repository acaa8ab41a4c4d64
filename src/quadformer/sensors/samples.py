"""The timestamped samples every source of flights produces (a live link, a telemetry log),
in SI units, world ENU, body FLU: what ``sensors.mavlink.decode`` gives (and re-exports), kept
apart from the MAVLink conversions so a reader finds the types by name."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Attitude", "Baro", "Estimate", "EstimatorRatios", "Gps", "GpsStatus", "Imu", "Mag", "Odometry", "Origin",
           "SystemTime"]


@dataclass(frozen=True, slots=True)
class Imu:
    t: float
    x: np.ndarray            # (6,) specific force m/s^2 and body rate rad/s, FLU
    source: str              # e.g. "HIGHRES_IMU#0"


@dataclass(frozen=True, slots=True)
class Mag:
    t: float
    field: np.ndarray        # (3,) gauss, FLU
    source: str


@dataclass(frozen=True, slots=True)
class Baro:
    t: float
    alt: float               # m, barometric altitude
    source: str


@dataclass(frozen=True, slots=True)
class Gps:
    t: float
    instance: int            # receiver: 0 GPS_RAW_INT, 1 GPS2_RAW
    fix_type: int            # GPS_FIX_TYPE (3: 3D fix)
    lat: float               # deg
    lon: float               # deg
    alt: float               # m, MSL
    vel: np.ndarray          # (3,) ENU m/s; NaN where not given (vertical always)
    eph: float               # m, horizontal accuracy (NaN: none)
    epv: float               # m, vertical accuracy (NaN: none)
    speed_acc: float         # m/s (NaN: none)
    satellites: float        # NaN when unknown


@dataclass(frozen=True, slots=True)
class GpsStatus:
    t: float
    instance: int            # receiver: 0 GPS_RAW_INT, 1 GPS2_RAW
    fix_type: int            # GPS_FIX_TYPE: 0/1 no fix, 2 2D, 3 3D, 4+ augmented
    satellites: float        # NaN when unknown
    eph: float               # m, horizontal accuracy (NaN: none)
    epv: float               # m, vertical accuracy (NaN: none)
    speed_acc: float         # m/s (NaN: none)


@dataclass(frozen=True, slots=True)
class Odometry:
    t: float
    pos: np.ndarray          # (3,) ENU, the odometry's own origin
    vel: np.ndarray          # (3,) ENU m/s
    q: np.ndarray            # (4,) xyzw, body FLU -> world ENU


@dataclass(frozen=True, slots=True)
class Attitude:
    t: float
    q: np.ndarray            # (4,) xyzw, body FLU -> world ENU


@dataclass(frozen=True, slots=True)
class Estimate:
    t: float
    kind: str                # "global" (lat, lon, alt) or "local" (the autopilot's local frame)
    pos: np.ndarray          # (3,) lat deg, lon deg, alt m (global) or ENU m (local)
    vel: np.ndarray          # (3,) ENU m/s


@dataclass(frozen=True, slots=True)
class EstimatorRatios:
    """The autopilot's own innovation test ratios, as its estimator status reports them: each the
    square root of a test ratio, the innovation over the gate's acceptance (1 at the gate; NaN
    where not sent)."""
    t: float                 # s, the vehicle's stamp (ESTIMATOR_STATUS); NaN: the message has none
    source: str              # "EKF_STATUS_REPORT" (ArduPilot) or "ESTIMATOR_STATUS" (PX4)
    vel: float               # velocity (ArduPilot: summed over its axes; PX4: the largest axis)
    pos_horiz: float         # horizontal position (likewise)
    pos_vert: float          # vertical position (the height source's)
    mag: float               # magnetometer, the largest axis (ArduPilot EKF2: the vector's length)
    terrain: float           # height above terrain (ArduPilot: range finder or flow, 0 when unused)
    airspeed: float          # true airspeed
    flags: int               # EKF_STATUS_FLAGS (ArduPilot) or ESTIMATOR_STATUS_FLAGS (PX4)
    gps_glitch: bool         # the flags' GPS glitch bit (EKF_GPS_GLITCHING, ESTIMATOR_GPS_GLITCH)
    pos_horiz_accuracy: float = math.nan    # m, 1-sigma (PX4 only)
    pos_vert_accuracy: float = math.nan     # m, 1-sigma (PX4 only)


@dataclass(frozen=True, slots=True)
class Origin:
    lat: float
    lon: float
    alt: float
    source: str              # "GPS_GLOBAL_ORIGIN" or "HOME_POSITION"


@dataclass(frozen=True, slots=True)
class SystemTime:
    unix_s: float            # s since 1970
    boot_s: float            # s since boot, at the same instant
