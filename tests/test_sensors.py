"""Part 3: GPS Gauss-Markov error, VIO drift and IMU noise levels."""

import numpy as np
import pytest
import torch

from quadformer.config import GPSConfig, IMUConfig, VIOConfig
from quadformer.rng import Stream, batch_generators
from quadformer.sensors import GPS, IMU, VIO


def test_gps_gauss_markov_error_statistics():
    cfg = GPSConfig(pos_std_h=1e-6, pos_std_v=1e-6, vel_std=0.1, gm_std=0.5, gm_tau=30.0)
    B, n = 200, 600
    gps = GPS(cfg, "gaussian", batch_generators(0, np.arange(B), Stream.GPS))
    zero = torch.zeros(B, 3, dtype=torch.float64)
    err = np.stack([gps.measure(zero, zero)[0].numpy() for _ in range(n)], axis=1)  # (B,n,3)
    assert err.std() == pytest.approx(0.5, rel=0.05)
    # lag-1 s autocorrelation of a first-order Gauss-Markov process: exp(-1/30)
    x = err[:, :-10].reshape(-1)
    y = err[:, 10:].reshape(-1)
    assert np.corrcoef(x, y)[0, 1] == pytest.approx(np.exp(-1.0 / 30.0), abs=0.01)


def test_vio_drift_is_about_one_percent_of_distance():
    B = 50
    pos0 = torch.zeros(B, 3, dtype=torch.float64)
    vio = VIO(VIOConfig(), "gaussian", batch_generators(0, np.arange(B), Stream.VIO), pos0)
    vel = torch.tensor([[5.0, 0.0, 0.0]], dtype=torch.float64).repeat(B, 1)
    q = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64).repeat(B, 1)
    for k in range(1, 401):  # 20 s at 20 Hz, 100 m travelled
        pos = vel * (k / 20.0)
        _, _, odom = vio.measure(pos, vel, q)
    drift = (odom - (pos - pos0)).norm(dim=-1).numpy()
    # drift accumulates along a wandering direction: at most 1 m, and most of it.
    assert np.all(drift <= 1.0 + 1e-9)
    assert drift.mean() > 0.6


def test_imu_noise_matches_rotorpy_scaling():
    cfg = IMUConfig(accel_bias_walk=0.0, gyro_bias_walk=0.0)
    B = 100
    imu = IMU(cfg, 100.0, batch_generators(0, np.arange(B), Stream.IMU), np.zeros((B, 3)), np.zeros((B, 3)))
    rot = torch.eye(3, dtype=torch.float64).repeat(B, 1, 1)
    acc = torch.zeros(B, 3, dtype=torch.float64)
    samples = np.stack([torch.cat(imu.measure(acc, acc, rot), -1).numpy() for _ in range(300)], 1)
    # level and still: specific force is +g on z; noise std density * sqrt(rate / 2)
    assert samples[..., 2].mean() == pytest.approx(9.81, abs=0.01)
    assert samples[..., 0].std() == pytest.approx(cfg.accel_noise_density * np.sqrt(50), rel=0.05)
    assert samples[..., 3].std() == pytest.approx(cfg.gyro_noise_density * np.sqrt(50), rel=0.05)
