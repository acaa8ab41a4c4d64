"""The receiver's clock in a log: fixes stamped at their epochs, the receiver's latency estimated."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from quadformer.estimator.filter_config import FilterConfig
from quadformer.logs import read_log
from quadformer.logs.receiver_clock import MAX_SHIFT_S, fix_epochs, latency, week_seconds
from quadformer.logs.replay import ekf_rows

FIX = Path(__file__).parent / "fixtures" / "logs"


def jittered(n=300, period=0.2, slope=1.0, seed=0):
    """Stamps of n fixes read by a driver: epochs every ``period`` s of GPS time on a clock
    running at ``slope``, plus a latency of 50 ms and a jitter of 0 to 60 ms."""
    rng = np.random.default_rng(seed)
    tow = 400000.0 + period * np.arange(n)
    t = 12.0 + slope * (tow - tow[0]) + 0.05 + rng.uniform(0.0, 0.06, n)
    return t, tow


def test_epochs_remove_the_jitter_and_follow_a_slow_clock():
    for slope in (1.0, 0.923):
        t, tow = jittered(slope=slope)
        new, keep, note = fix_epochs(t, tow)
        assert keep.all()
        steps = np.diff(new)
        # every interval is the receiver's 0.2 s on the autopilot's clock, to 10 microseconds
        assert np.allclose(steps, 0.2 * slope, atol=1e-5)
        # the fixes read the soonest (the lowest 2 % of the lag) define the offset: none moves later
        assert np.quantile(t - new, 0.02) == pytest.approx(0.0, abs=1e-9)
        assert np.all(new <= t + 2e-3)       # later than read by a few ms at most (the lowest 2 % of the lag)
        assert "epochs" in note and ("slow" in note) == (slope != 1.0)


def test_repeated_and_late_fixes():
    t, tow = jittered()
    t[0] = t[1] - 0.15                      # read long after its epoch: the first fix of a receiver starting
    tow[0] = tow[1] - 5.0
    t2 = np.insert(t, 51, t[50] + 0.03)     # fix 50 read again, the same time of week
    tow2 = np.insert(tow, 51, tow[50])
    new, keep, note = fix_epochs(t2, tow2)
    assert not keep[51] and keep.sum() == len(t2) - 1
    assert new[0] == t2[0]                  # further than MAX_SHIFT_S from the line: its stamp kept
    assert abs(t2[0] - (new[1] - 5.0)) > MAX_SHIFT_S
    assert np.all(np.diff(new[keep]) > 0)
    assert "read twice" in note and "keep their stamps" in note


@pytest.mark.parametrize("case", ["few", "no time", "going back", "exact"])
def test_unusable_or_needless_time_of_week_leaves_the_stamps(case):
    t, tow = jittered()
    if case == "few":
        t, tow = t[:10], tow[:10]
    elif case == "no time":
        tow = week_seconds(np.zeros(len(t)), tow * 1e3)
        assert np.isnan(tow).all()
    elif case == "going back":
        tow[100:] -= 30.0
    else:                                   # already at the epochs: nothing to remove
        t = 12.0 + (tow - tow[0])
    new, keep, note = fix_epochs(t, tow)
    assert np.array_equal(new, t) and keep.all() and note is None


def test_week_seconds():
    out = week_seconds(np.array([1815, 0, 1815]), np.array([6283000, 1000, 0]))
    assert out[0] == pytest.approx(1815 * 604800 + 6283.0)
    assert np.isnan(out[1]) and np.isnan(out[2])


def kinematic_rows(delay, n=900, rate=5.0, seed=3):
    """Rows of a filter replay over a manoeuvring flight whose fixes lag by ``delay``: the
    filter's propagation over each interval is the true velocity change (an exact IMU), its
    posterior halfway between its prediction and the fix."""
    rng = np.random.default_rng(seed)
    fine = 200.0
    tt = np.arange(0.0, n / rate + 2.0, 1.0 / fine)
    acc = np.zeros((len(tt), 2))             # 2 m/s^2 of acceleration changing within about 0.5 s
    kick = rng.normal(0.0, 2.0 * np.sqrt(2.0 / (0.5 * fine)), (len(tt), 2))
    for i in range(1, len(tt)):
        acc[i] = acc[i - 1] * (1.0 - 1.0 / (0.5 * fine)) + kick[i]
    v = np.cumsum(acc, axis=0) / fine
    t = 1.0 + np.arange(n) / rate
    truth = np.column_stack([np.interp(t, tt, v[:, i]) for i in range(2)])
    lagged = np.column_stack([np.interp(t - delay, tt, v[:, i]) for i in range(2)])
    gps = lagged + rng.normal(0.0, 0.05, (n, 2))
    post = np.zeros((n, 2))
    pred = np.zeros((n, 2))
    for k in range(n):
        pred[k] = gps[0] if k == 0 else post[k - 1] + (truth[k] - truth[k - 1])
        post[k] = pred[k] + 0.5 * (gps[k] - pred[k])
    return pd.DataFrame({"t": t, "gps_vel_x": gps[:, 0], "gps_vel_y": gps[:, 1],
                         "res_gps_r_vx": gps[:, 0] - pred[:, 0], "res_gps_r_vy": gps[:, 1] - pred[:, 1],
                         "est_vel_x": post[:, 0], "est_vel_y": post[:, 1], "in_air": 1.0})


@pytest.mark.parametrize("delay", [0.1, 0.2])
def test_latency_found_on_a_manoeuvring_flight(delay):
    assert latency(kinematic_rows(delay)) == pytest.approx(delay, abs=0.021)


def test_latency_none_without_a_lag_or_data():
    assert latency(kinematic_rows(0.0)) is None
    assert latency(kinematic_rows(0.1).iloc[:30]) is None
    assert latency(kinematic_rows(0.1).drop(columns="est_vel_x")) is None


def test_a_replayed_log_stamped_at_epochs_and_without_a_latency_setting(tmp_path):
    """The project's own DataFlash log: its fixes stamped when measured (no jitter to remove), and
    ``GPS_DELAY_MS`` 0 (no setting), so the replay estimates the latency: a smooth simulated
    circle shows none, and the replay is the one fused at the stamps."""
    log = read_log(FIX / "sim_copter.bin")
    assert not any("epochs" in n for n in log.notes)
    assert "gps_delay_s" not in log.vehicle
    f = ekf_rows(log, 0, FilterConfig(sensors="gps+imu+mag+baro"))
    g = ekf_rows(log, 0, FilterConfig(sensors="gps+imu+mag+baro", gps_delay_s=0.0))
    assert not any("latency" in n for n in f.notes)
    pd.testing.assert_frame_equal(f.rows, g.rows)
