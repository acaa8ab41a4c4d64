"""Part 3: GPS Gauss-Markov error, VIO drift, IMU noise levels, magnetometer and barometer."""

import numpy as np
import pytest
import roma
import torch

from quadformer.config import BaroConfig, GPSConfig, IMUConfig, MagConfig, VIOConfig
from quadformer.rng import Stream, batch_generators
from quadformer.sensors import GPS, IMU, VIO, Barometer, Magnetometer


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


def _yaw(deg: float, B: int) -> torch.Tensor:
    """Level body-to-world rotations with heading ``deg`` (0: east, 90: north), (B,3,3)."""
    rv = torch.tensor([[0.0, 0.0, np.deg2rad(deg)]], dtype=torch.float64).repeat(B, 1)
    return roma.rotvec_to_rotmat(rv)


def test_magnetometer_sees_the_earth_field_in_body_axes():
    """ENU world, FLU body, field 0.22 G north and 0.42 G down: heading east, north is on the
    left (+y); heading north, it is ahead (+x); down is -z whatever the heading."""
    B = 4
    cfg = MagConfig(noise_std=1e-12, bias_std=0.0)
    mag = Magnetometer(cfg, "gaussian", batch_generators(0, np.arange(B), Stream.MAG))
    np.testing.assert_allclose(mag.measure(_yaw(0.0, B)).numpy(), [[0.0, 0.22, -0.42]] * B, atol=1e-9)
    np.testing.assert_allclose(mag.measure(_yaw(90.0, B)).numpy(), [[0.22, 0.0, -0.42]] * B, atol=1e-9)
    # magnetic north 90 deg east of true north: heading east faces it
    east = Magnetometer(MagConfig(noise_std=1e-12, bias_std=0.0, declination_deg=90.0), "gaussian",
                        batch_generators(0, np.arange(B), Stream.MAG))
    np.testing.assert_allclose(east.measure(_yaw(0.0, B)).numpy(), [[0.22, 0.0, -0.42]] * B, atol=1e-9)
    # heading east, rolled 90 deg to the right: body +y (left) points up, +z points south
    rolled = roma.rotvec_to_rotmat(torch.tensor([[np.pi / 2, 0.0, 0.0]], dtype=torch.float64)).repeat(B, 1, 1)
    np.testing.assert_allclose(mag.measure(rolled).numpy(), [[0.0, -0.42, -0.22]] * B, atol=1e-9)


def test_magnetometer_bias_is_constant_per_flight_and_noise_has_its_std():
    B, n = 1000, 100
    cfg = MagConfig(noise_std=0.005, bias_std=0.01, bias_walk=0.0)
    mag = Magnetometer(cfg, "laplace", batch_generators(1, np.arange(B), Stream.MAG))
    x = np.stack([mag.measure(_yaw(30.0, B)).numpy() for _ in range(n)], 1)       # (B,n,3)
    truth = (roma.rotvec_to_rotmat(torch.tensor([0.0, 0.0, np.deg2rad(30.0)], dtype=torch.float64)).T
             @ torch.tensor(cfg.field_enu, dtype=torch.float64)).numpy()
    bias = x.mean(1) - truth
    assert bias.std() == pytest.approx(0.01, rel=0.05)
    assert (x - x.mean(1, keepdims=True)).std() == pytest.approx(0.005, rel=0.02)


def test_barometer_height_and_gauss_markov_bias():
    cfg = BaroConfig(noise_std=1e-9, gm_std=0.5, gm_tau=20.0, rate_hz=25.0)
    B, n = 200, 1000
    baro = Barometer(cfg, "gaussian", batch_generators(0, np.arange(B), Stream.BARO))
    pos = torch.tensor([[3.0, -2.0, 12.0]], dtype=torch.float64).repeat(B, 1)
    h = np.stack([baro.measure(pos)[:, 0].numpy() for _ in range(n)], 1)           # (B,n)
    err = h - 12.0
    assert abs(err.mean()) < 0.05
    assert err.std() == pytest.approx(0.5, rel=0.05)
    # lag of 1 s (25 samples): autocorrelation exp(-1/20)
    lag = np.corrcoef(err[:, :-25].reshape(-1), err[:, 25:].reshape(-1))[0, 1]
    assert lag == pytest.approx(np.exp(-1 / 20), abs=0.01)
