"""The sensors' configuration: GPS, visual odometry, magnetometer, barometer and IMU, each a
frozen dataclass validated at construction."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from quadformer.config.base import _non_negative, _positive, _require


@dataclass(frozen=True)
class GPSConfig:
    rate_hz: float = 10.0          # Hz, GPS solution rate
    pos_std_h: float = 0.5         # m, white noise std, horizontal axes
    pos_std_v: float = 1.0         # m, white noise std, vertical axis
    vel_std: float = 0.1           # m/s, white noise std, each axis
    gm_std: float = 0.5            # m, Gauss-Markov position error std (0 disables it)
    gm_tau: float = 30.0           # s, Gauss-Markov time constant

    def __post_init__(self) -> None:
        _positive("gps.rate_hz", self.rate_hz)
        _positive("gps.pos_std_h", self.pos_std_h)
        _positive("gps.pos_std_v", self.pos_std_v)
        _positive("gps.vel_std", self.vel_std)
        _non_negative("gps.gm_std", self.gm_std)
        _positive("gps.gm_tau", self.gm_tau)


@dataclass(frozen=True)
class VIOConfig:
    rate_hz: float = 20.0          # Hz, stereo VIO output rate
    vel_std: float = 0.05          # m/s, velocity noise std, each axis
    att_std_deg: float = 0.5       # deg, attitude noise std, each axis
    drift_fraction: float = 0.01   # position drift per metre travelled (odometry frame)

    def __post_init__(self) -> None:
        _positive("vio.rate_hz", self.rate_hz)
        _positive("vio.vel_std", self.vel_std)
        _positive("vio.att_std_deg", self.att_std_deg)
        _non_negative("vio.drift_fraction", self.drift_fraction)


@dataclass(frozen=True)
class MagConfig:
    """Three-axis magnetometer: body-frame (FLU) Earth field, hard-iron bias and noise.

    The Earth field in the world frame (ENU) is ``field_h`` pointing to magnetic north
    (``declination_deg`` east of true north) and ``field_v`` pointing down."""
    rate_hz: float = 50.0          # Hz, sample rate
    noise_std: float = 0.005       # gauss, white noise std, each axis
    bias_std: float = 0.01         # gauss, constant hard-iron bias std per flight, each axis
    bias_walk: float = 0.0         # gauss/sqrt(s), bias random walk (0 disables it)
    field_h: float = 0.22          # gauss, horizontal Earth field (towards magnetic north)
    field_v: float = 0.42          # gauss, vertical Earth field (positive down)
    declination_deg: float = 0.0   # deg, magnetic north east of true north

    def __post_init__(self) -> None:
        _positive("mag.rate_hz", self.rate_hz)
        _positive("mag.noise_std", self.noise_std)
        _non_negative("mag.bias_std", self.bias_std)
        _non_negative("mag.bias_walk", self.bias_walk)
        _positive("mag.field_h", self.field_h)
        _require(isinstance(self.field_v, (int, float)) and math.isfinite(self.field_v), "mag.field_v",
                 f"must be a finite number, got {self.field_v!r}")
        _require(isinstance(self.declination_deg, (int, float)) and -180.0 <= self.declination_deg <= 180.0,
                 "mag.declination_deg", f"must be in [-180, 180], got {self.declination_deg!r}")

    @property
    def field_enu(self) -> tuple[float, float, float]:
        """The Earth field in the world frame (east, north, up), gauss."""
        d = math.radians(self.declination_deg)
        return (self.field_h * math.sin(d), self.field_h * math.cos(d), -self.field_v)


@dataclass(frozen=True)
class BaroConfig:
    """Barometric height: the world-frame height (ENU z) plus a Gauss-Markov bias and noise."""
    rate_hz: float = 25.0          # Hz, sample rate
    noise_std: float = 0.4         # m, white noise std
    gm_std: float = 0.5            # m, Gauss-Markov bias std (0 disables it)
    gm_tau: float = 60.0           # s, Gauss-Markov time constant

    def __post_init__(self) -> None:
        _positive("baro.rate_hz", self.rate_hz)
        _positive("baro.noise_std", self.noise_std)
        _non_negative("baro.gm_std", self.gm_std)
        _positive("baro.gm_tau", self.gm_tau)


@dataclass(frozen=True)
class IMUConfig:
    """IMU error model (rotorpy's: white noise scaled by sqrt(rate/2), bias random walk)."""
    accel_noise_density: float = 0.02    # m/s^2/sqrt(Hz)
    gyro_noise_density: float = 0.002    # rad/s/sqrt(Hz)
    accel_bias_walk: float = 1e-3        # m/s^3/sqrt(Hz), bias random walk
    gyro_bias_walk: float = 1e-4         # rad/s^2/sqrt(Hz), bias random walk
    accel_bias_std: float = 0.05         # m/s^2, initial bias std (per flight)
    gyro_bias_std: float = 0.005         # rad/s, initial bias std (per flight)

    def __post_init__(self) -> None:
        for f in fields(self):
            _non_negative(f"imu.{f.name}", getattr(self, f.name))
