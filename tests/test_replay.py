"""The EKF on its own over recorded sensor streams reproduces the closed loop's residues."""

import numpy as np
import pytest

from quadformer.config import AttackConfig, SimConfig
from quadformer.estimator.replay import StreamError, run_ekf
from quadformer.simulation.closed_loop import simulate_batch

CFG = SimConfig(model="II", noise="exponential", flights=2, duration=8.0, seed=9,
                attack=AttackConfig(kind="ramp", onset=(3.0, 4.0), fraction=1.0))


@pytest.fixture(scope="module")
def run():
    return simulate_batch(CFG, np.arange(2), np.array([True, False]), record_sensors=True)


def _replay(s, **over):
    args = dict(ekf0=s["ekf0"], nm=s["noise"], dt=s["dt"], imu_t=s["imu_t"], imu=s["imu"], vio_t=s["vio_t"],
                vio=s["vio"], gps_t=s["gps_t"], gps=s["gps"])
    return run_ekf(**{**args, **over})


def test_replay_reproduces_closed_loop_residues_bit_for_bit(run):
    out = _replay(run["sensors"])
    for name in ("res_gps_r", "res_gps_w", "res_gps_s", "res_gps_nis", "res_gps_corr", "res_vio_r",
                 "res_vio_nis", "res_vio_nis_mean", "est_pos", "est_vel"):
        assert np.array_equal(out[name], run[name]), name


def test_bad_streams_are_named(run):
    s = run["sensors"]
    imu = s["imu"].clone()
    imu[1, 40, 2] = float("nan")
    with pytest.raises(StreamError, match="imu: non-finite sample at index 40"):
        _replay(s, imu=imu)
    t = s["imu_t"].copy()
    t[100:] += 0.5
    with pytest.raises(StreamError, match="imu: gap of 0.510 s"):
        _replay(s, imu_t=t)
    g = s["gps_t"].copy()
    g[5] = g[4]
    with pytest.raises(StreamError, match="gps: timestamps must increase"):
        _replay(s, gps_t=g)
    with pytest.raises(StreamError, match="vio: 3 timestamps"):
        _replay(s, vio_t=s["vio_t"][:3])
