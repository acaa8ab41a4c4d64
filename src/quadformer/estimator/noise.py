"""The filter's noise as numpy arrays (``Noise``), and the noise matched to a simulation's sensors
(``simulated_noise``), without torch: a log replayed with a simulation's tuning needs no torch
filter. ``eskf.noise_model`` gives the same values as torch tensors."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from quadformer.config import BaroConfig, MagConfig


@dataclass(frozen=True)
class Noise:
    """The filter's noise as numpy arrays (the fields of ``eskf.NoiseModel``): per-step process
    noise stds, measurement noise stds, and the Earth field the magnetometer heading is
    measured against (None until known)."""
    accel_std: float
    gyro_std: float
    accel_walk: float
    gyro_walk: float
    gps_std: np.ndarray       # (6,) position m, velocity m/s
    vio_std: np.ndarray       # (6,) velocity m/s, attitude rad
    mag_std: np.ndarray       # (1,) heading, rad
    baro_std: np.ndarray      # (1,) height, m
    mag_field: np.ndarray | None = None   # (3,) world frame (ENU), gauss

    @classmethod
    def of(cls, nm: Any) -> "Noise":
        """The arrays of a torch ``eskf.NoiseModel`` (absent measurement stds: 1)."""
        a = lambda t, k: np.ones(k) if t is None else t.detach().cpu().numpy().astype(float)  # noqa: E731
        return cls(float(nm.accel_std), float(nm.gyro_std), float(nm.accel_walk), float(nm.gyro_walk),
                   a(nm.gps_std, 6), a(nm.vio_std, 6), a(nm.mag_std, 1), a(nm.baro_std, 1),
                   None if nm.mag_field is None else a(nm.mag_field, 3))


def simulated_noise(imu_cfg, gps_cfg, vio_cfg, ekf_cfg, imu_rate_hz: float, mag_cfg=None, baro_cfg=None) -> Noise:
    """Filter noise matched to the sensor configuration unless ``ekf_cfg`` overrides it
    (``mag_cfg`` and ``baro_cfg``: default ``MagConfig()`` and ``BaroConfig()``); per IMU
    sample at ``imu_rate_hz``."""
    mag_cfg = MagConfig() if mag_cfg is None else mag_cfg
    baro_cfg = BaroConfig() if baro_cfg is None else baro_cfg
    scale = float(np.sqrt(imu_rate_hz / 2.0))
    h = ekf_cfg.gps_pos_std_h or float(np.hypot(gps_cfg.pos_std_h, gps_cfg.gm_std))
    vv = ekf_cfg.gps_pos_std_v or float(np.hypot(gps_cfg.pos_std_v, gps_cfg.gm_std))
    gv = ekf_cfg.gps_vel_std or gps_cfg.vel_std
    vvel = ekf_cfg.vio_vel_std or vio_cfg.vel_std
    vatt = np.deg2rad(ekf_cfg.vio_att_std_deg or vio_cfg.att_std_deg)
    # heading: the horizontal field's noise and bias across it, over its length
    heading = (np.deg2rad(ekf_cfg.mag_heading_std_deg) if ekf_cfg.mag_heading_std_deg
               else float(np.hypot(mag_cfg.noise_std, mag_cfg.bias_std)) / mag_cfg.field_h)
    height = ekf_cfg.baro_std or float(np.hypot(baro_cfg.noise_std, baro_cfg.gm_std))
    f64 = lambda v: np.array(v, dtype=np.float64)   # noqa: E731
    return Noise(
        accel_std=imu_cfg.accel_noise_density * scale,
        gyro_std=imu_cfg.gyro_noise_density * scale,
        accel_walk=imu_cfg.accel_bias_walk / scale,
        gyro_walk=imu_cfg.gyro_bias_walk / scale,
        gps_std=f64([h, h, vv, gv, gv, gv]),
        vio_std=f64([vvel] * 3 + [vatt] * 3),
        mag_std=f64([heading]),
        baro_std=f64([height]),
        mag_field=f64(mag_cfg.field_enu),
    )
