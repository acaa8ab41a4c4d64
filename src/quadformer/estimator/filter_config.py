"""How a real vehicle's sensors are fused (``FilterConfig``: PX4 EKF2's defaults, or the tuning of
a simulation), and the noise model it gives the filter for IMU steps of a given length."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from quadformer.config import SENSOR_NAMES
from quadformer.estimator.noise import Noise, simulated_noise

if TYPE_CHECKING:
    from quadformer.estimator.eskf import NoiseModel


MAX_GPS_DELAY = 0.5                  # s, the largest receiver latency the stream compensates
#: the least rate (Hz) per stream the filter needs live (a stream more than 10% slower is warned about)
MIN_RATES = {"imu": 50.0, "gps": 5.0, "baro": 10.0, "vio": 20.0}
RATE_TOLERANCE = 0.9     # a stream counts as at its least rate down to 90% of it
#: Hz, the slowest IMU a recorded log is replayed with (ArduPilot logs its IMU at 25 Hz by default;
#: a telemetry link's 1 to 10 Hz cannot propagate the filter)
MIN_REPLAY_IMU_HZ = 20.0


@dataclass(frozen=True)
class FilterConfig:
    """How a real vehicle's sensors are fused (a log replayed, a live link). Noise defaults are PX4 EKF2's parameter
    defaults (EKF2_ACC_NOISE, EKF2_GYR_NOISE, EKF2_ACC_B_NOISE, EKF2_GYR_B_NOISE,
    EKF2_GPS_P_NOISE, EKF2_GPS_V_NOISE, EKF2_BARO_NOISE, EKF2_HEAD_NOISE); ``matching`` takes
    a simulation's instead. IMU noise is per filter step at ``imu_rate_hz`` and is scaled to
    keep its density when a log's IMU is slower."""
    sensors: str | None = None      # e.g. "gps+imu+mag+baro"; None: every sensor the log has
    #: a log replay fuses those of ``sensors`` the log has (GPS and IMU still needed) instead of
    #: refusing a log that lacks one (the shipped detectors: a log without a compass, say)
    sensors_where_logged: bool = False
    imu_rate_hz: float = 100.0      # Hz, IMU averaged down to at most this rate
    gps_rate_hz: float = 10.0       # Hz, at most this many fixes fused per second
    accel_noise: float = 0.35       # m/s^2, accelerometer noise per filter step
    gyro_noise: float = 0.015       # rad/s, gyro noise per filter step
    accel_bias_walk: float = 3e-3   # m/s^3, accelerometer bias random walk
    gyro_bias_walk: float = 1e-3    # rad/s^2, gyro bias random walk
    gps_pos_noise: float = 0.5      # m, floor of the horizontal position std (eph used when larger)
    gps_alt_noise: float = 0.75     # m, floor of the vertical position std (epv used when larger)
    gps_vel_noise: float = 0.3      # m/s, floor of the velocity std (speed accuracy used when larger)
    baro_noise: float = 3.5         # m, barometric height std
    heading_noise: float = 0.3      # rad, magnetometer heading std
    vio_vel_noise: float = 0.1      # m/s, visual odometry velocity std
    vio_att_noise_deg: float = 2.0  # deg, visual odometry attitude std
    init_vel_std: float = 0.5       # m/s, initial velocity uncertainty
    init_att_std_deg: float = 5.0   # deg, initial roll/pitch/yaw uncertainty (given an attitude)
    init_yaw_std_deg: float = 60.0  # deg, initial yaw uncertainty without an attitude or a magnetometer
    init_mag_yaw_std_deg: float = 20.0  # deg, initial yaw uncertainty from the magnetic heading
                                        # (the declination is not known to the filter)
    accel_bias_std: float = 0.2     # m/s^2, initial accelerometer bias uncertainty
    gyro_bias_std: float = 0.01     # rad/s, initial gyro bias uncertainty
    receiver_accuracy: bool = True  # use the receiver's eph/epv/speed accuracy when above the floors
    max_gap_s: float = 0.5          # s, the longest IMU gap the filter propagates across
    min_segment_s: float = 3.0      # s of GPS a segment needs to be replayed
    #: s, how long before its stamp a fix was measured (the receiver's latency; PX4
    #: EKF2_GPS_DELAY, ArduPilot GPS_DELAY_MS). None: a log's own autopilot setting where it
    #: records one, else 0 (a live link: 0)
    gps_delay_s: float | None = None

    @classmethod
    def matching(cls, sim: dict[str, Any], **overrides: Any) -> "FilterConfig":
        """The filter tuning of simulated data (a dataset's resolved ``SimConfig`` as a dict):
        the residues of a replayed log then have the scale of the residues a detector was
        fit on. The simulated noise is each fix's floor; a receiver that states a worse
        accuracy (eph, epv, speed accuracy) is trusted that much less, as the autopilot trusts
        it, so the whitened residues keep the scale the detector expects: with the floor
        alone, a receiver of 3 m reads as a 3 m spoof to a detector fit on a simulated 0.5 m."""
        from quadformer.config import SimConfig

        cfg = SimConfig.from_dict(sim)
        nm = simulated_noise(cfg.imu, cfg.gps, cfg.vio, cfg.ekf, 1.0 / cfg.dt, cfg.mag, cfg.baro)
        g = nm.gps_std.tolist()
        v = nm.vio_std.tolist()
        values = dict(
            sensors=None, imu_rate_hz=1.0 / cfg.dt, gps_rate_hz=cfg.gps.rate_hz,
            accel_noise=nm.accel_std, gyro_noise=nm.gyro_std,
            accel_bias_walk=nm.accel_walk / cfg.dt, gyro_bias_walk=nm.gyro_walk / cfg.dt,
            gps_pos_noise=g[0], gps_alt_noise=g[2], gps_vel_noise=g[3],
            baro_noise=float(nm.baro_std[0]), heading_noise=float(nm.mag_std[0]),
            vio_vel_noise=v[0], vio_att_noise_deg=float(np.rad2deg(v[3])),
            init_vel_std=cfg.ekf.init_vel_std, init_att_std_deg=cfg.ekf.init_att_std_deg,
            accel_bias_std=cfg.imu.accel_bias_std, gyro_bias_std=cfg.imu.gyro_bias_std)
        values.update(overrides)
        return cls(**values)

    def __post_init__(self) -> None:
        d = self.gps_delay_s
        if d is not None and not (isinstance(d, (int, float)) and math.isfinite(d) and 0.0 <= d <= MAX_GPS_DELAY):
            raise ValueError(f"filter.gps_delay_s must be a number of seconds from 0 to {MAX_GPS_DELAY:g}, got {d!r}")
        for name in ("imu_rate_hz", "gps_rate_hz", "accel_noise", "gyro_noise", "gps_pos_noise",
                     "gps_alt_noise", "gps_vel_noise", "baro_noise", "heading_noise", "vio_vel_noise",
                     "vio_att_noise_deg", "init_vel_std", "init_att_std_deg", "init_yaw_std_deg",
                     "max_gap_s", "min_segment_s", "accel_bias_std", "gyro_bias_std"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"filter.{name} must be a positive number, got {v!r}")
        for name in ("accel_bias_walk", "gyro_bias_walk"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"filter.{name} must be a non-negative number, got {v!r}")
        if self.sensors is not None:
            parts = set(self.sensors.split("+"))
            unknown = parts - set(SENSOR_NAMES)
            if unknown or not {"gps", "imu"} <= parts:
                raise ValueError(f"filter.sensors: {self.sensors!r} must join gps, imu and any of vio, mag, "
                                 f"baro with '+' (unknown: {', '.join(sorted(unknown)) or 'none'})")


def noise_for(config: FilterConfig, dt: float, mag_field: np.ndarray | None = None) -> Noise:
    """The filter's noise for IMU steps of dt seconds: the configured per-step noise at
    ``imu_rate_hz``, scaled to the same density at dt."""
    c = config
    density = math.sqrt(1.0 / (c.imu_rate_hz * dt))      # per-step std ~ 1/sqrt(dt)
    return Noise(
        accel_std=c.accel_noise * density, gyro_std=c.gyro_noise * density,
        accel_walk=c.accel_bias_walk * dt, gyro_walk=c.gyro_bias_walk * dt,
        gps_std=np.array([c.gps_pos_noise, c.gps_pos_noise, c.gps_alt_noise] + [c.gps_vel_noise] * 3),
        vio_std=np.array([c.vio_vel_noise] * 3 + [np.deg2rad(c.vio_att_noise_deg)] * 3),
        mag_std=np.array([c.heading_noise]), baro_std=np.array([c.baro_noise]),
        mag_field=None if mag_field is None else np.asarray(mag_field, dtype=float))


def noise_model_for(config: FilterConfig, dt: float, mag_field: np.ndarray | None = None) -> NoiseModel:
    """``noise_for`` as the torch filter's ``eskf.NoiseModel``."""
    import torch

    from quadformer.estimator.eskf import NoiseModel

    f64 = lambda v: None if v is None else torch.tensor(v, dtype=torch.float64)   # noqa: E731
    n = noise_for(config, dt, mag_field)
    return NoiseModel(accel_std=n.accel_std, gyro_std=n.gyro_std, accel_walk=n.accel_walk, gyro_walk=n.gyro_walk,
                      gps_std=f64(n.gps_std), vio_std=f64(n.vio_std), mag_std=f64(n.mag_std),
                      baro_std=f64(n.baro_std), mag_field=f64(n.mag_field))
