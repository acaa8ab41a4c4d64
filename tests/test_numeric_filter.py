"""The compiled filter (``estimator.numeric``) against the torch filter it mirrors, on real
logs: a real PX4 flight (pyulog's sample with events, GPS, IMU, magnetometer, barometer) and
the project's own simulated ArduCopter DataFlash log, each replayed through ``ResidueStream``
with both backends. Simulated flights of every sensor configuration: tests/test_replay.py."""

from __future__ import annotations

import numpy as np
import pytest

from logs_support import FIX
from quadformer.estimator.feed import GapError, StreamError
from quadformer.estimator.filter_config import FilterConfig, noise_for
from quadformer.estimator.numeric.filter import NumericFilter
from quadformer.estimator.online import ResidueStream
from quadformer.logs import read_log
from quadformer.logs.replay import ekf_rows

RTOL = ATOL = 1e-6    # measured: 5e-9 relative at worst on these logs


@pytest.mark.parametrize("name", ["sample_px4_events.ulg", "sim_copter.bin"])
def test_a_log_replayed_compiled_gives_the_torch_residues(name):
    log = read_log(FIX / name)
    fast = ekf_rows(log, 0, FilterConfig(), backend="numeric")
    ref = ekf_rows(log, 0, FilterConfig(), backend="torch")
    a, b = fast.rows, ref.rows
    assert list(a.columns) == list(b.columns) and len(a) == len(b) > 100
    assert fast.notes == ref.notes and fast.sensors == ref.sensors == "gps+imu+mag+baro"
    assert np.array_equal(a["t"], b["t"])
    cols = [c for c in a.columns if c.startswith(("res_", "est_"))]
    assert any(c.startswith("res_mag_") for c in cols) and any(c.startswith("res_baro_") for c in cols)
    for c in cols:
        np.testing.assert_allclose(a[c].to_numpy(float), b[c].to_numpy(float), rtol=RTOL, atol=ATOL, err_msg=c)
    assert a["res_gps_nis"].std() > 0.1            # real, moving residues


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="backend: 'jax'"):
        ResidueStream(FilterConfig(), "gps+imu", backend="jax")
    n = 1
    f = NumericFilter(np.zeros((n, 3)), np.zeros((n, 3)), [[0, 0, 0, 1.0]], np.eye(15)[None], noise_for(FilterConfig(), 0.01),
                      0.01, 0.0, 10.0, ("baro",), 0.1)
    with pytest.raises(ValueError, match="vio: not a stream of this filter"):
        f.push("vio", 0.0, np.zeros((1, 7)))
    f.imu(0.01, np.r_[0, 0, 9.81, 0, 0, 0])
    with pytest.raises(GapError, match="gap of 0.500 s"):
        f.imu(0.51, np.zeros(6))
    f.push("baro", 0.02, np.array([[np.nan]]))
    with pytest.raises(StreamError, match=r"baro: the filter's update failed at t = 0.020 s"):
        f.imu(0.02, np.r_[0, 0, 9.81, 0, 0, 0])
    with pytest.raises(ValueError, match="aiding: unknown sensor 'lidar'"):
        NumericFilter(np.zeros((1, 3)), np.zeros((1, 3)), [[0, 0, 0, 1.0]], np.eye(15)[None],
                      noise_for(FilterConfig(), 0.01), 0.01, aiding=("lidar",))
