"""The sensor noise a log shows, as the filter meets it (``logs.noise``): the receiver's white
velocity and position noise and the IMU's share of one GPS interval, recovered from simulated
flights the project writes as ArduPilot logs, whose noise is known."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from quadformer.logs import read_log
from quadformer.logs.noise import estimate_noise, interval_noise

FIXTURE = "tests/fixtures/logs/sim_copter.bin"     # GPS 10 Hz, white 0.5 m and 0.1 m/s, IMU 0.02 m/s^2/sqrt(Hz)


def test_a_receivers_white_noise_is_recovered_from_its_neighbouring_intervals():
    f = interval_noise(read_log(FIXTURE))
    assert f is not None and f.intervals > 500 and f.interval_s == pytest.approx(0.1, abs=1e-3)
    assert f.gps_vel == pytest.approx(0.1, rel=0.2)
    assert f.gps_pos_h == pytest.approx(0.5, rel=0.2)
    # the IMU's 0.006 m/s per interval hides under the receiver's 0.14: its share is an upper bound
    assert f.accel_density <= f.spread / np.sqrt(f.interval_s) + 1e-9


def _written(tmp_path, noise: dict) -> object:
    from quadformer.config import SimConfig, merge
    from quadformer.experiments.flight_logs import simulate_with_logs

    cfg = SimConfig.from_dict(merge(noise, {"flights": 1, "duration": 60.0, "seed": 8,
                                            "sensors": "gps+imu+mag+baro"}))
    _, logs, _ = simulate_with_logs(cfg, tmp_path / "quiet", ("dataflash",), name="quiet")
    return read_log(logs / "quiet_0000.bin")


def test_a_noisy_imu_under_a_quiet_receiver_is_measured_over_the_interval(tmp_path):
    log = _written(tmp_path, {"gps": {"vel_std": 0.02, "pos_std_h": 0.05, "gm_std": 0.0},
                              "imu": {"accel_noise_density": 0.4}})
    f = interval_noise(log)
    assert f is not None
    assert f.accel_density == pytest.approx(0.4, rel=0.2)
    assert f.gps_vel < 0.06 and f.gps_pos_h < 0.1
    est = estimate_noise([log])
    assert est.accel_from == "gps intervals" and est.intervals == f.intervals
    assert est.accel_density == pytest.approx(f.accel_density)
    assert est.gps_vel == pytest.approx(max(f.gps_vel, 0.02))


def test_a_log_without_the_attitude_falls_back_to_the_samples_and_says_so():
    log = read_log(FIXTURE)
    bare = dataclasses.replace(log, attitude=None)
    assert interval_noise(bare) is None
    est = estimate_noise([bare])
    assert est.accel_from == "imu samples" and est.intervals == 0
    both = estimate_noise([log, bare])
    assert both.accel_from == "mixed" and both.intervals == interval_noise(log).intervals
