"""The receiver's clock in a log: fixes stamped at their epochs, the receiver's latency estimated."""

from __future__ import annotations

import dataclasses
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


def manoeuvring_log(delay, seconds=240.0, seed=3, noise=0.05):
    """A log of a vehicle level and facing east, accelerating in the horizontal plane (about
    2 m/s^2 changing within about 0.5 s), its IMU exact at 100 Hz, its 5 Hz fixes' velocity
    measured ``delay`` seconds before their stamps, with ``noise`` m/s of white noise."""
    from quadformer.logs.flightlog import FlightLog, make_stream

    rng = np.random.default_rng(seed)
    ti = np.arange(0.0, seconds, 0.01)
    acc = np.zeros((len(ti), 2))
    kick = rng.normal(0.0, 2.0 * np.sqrt(2.0 / 50.0), (len(ti), 2))
    for i in range(1, len(ti)):
        acc[i] = acc[i - 1] * (1.0 - 1.0 / 50.0) + kick[i]
    vel = np.concatenate([[np.zeros(2)], np.cumsum(0.5 * (acc[1:] + acc[:-1]) * 0.01, axis=0)])
    t = np.arange(1.0, seconds, 0.2)
    v = np.stack([np.interp(t - delay, ti, vel[:, k]) for k in range(2)], axis=1) + rng.normal(0.0, noise, (len(t), 2))
    zero = np.zeros(len(t))
    imu = make_stream("imu", ti, {"ax": acc[:, 0], "ay": acc[:, 1], "az": 9.80665, "gx": 0.0, "gy": 0.0, "gz": 0.0})
    gps = make_stream("gps", t, {"x": zero, "y": zero, "z": zero, "vx": v[:, 0], "vy": v[:, 1], "vz": zero,
                                 "lat": 47.0, "lon": 8.0, "alt": 400.0, "fix_type": 3.0})
    att = make_stream("attitude", ti[::10], {"qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0})
    return FlightLog("arrays", Path("manoeuvres"), imu=imu, gps=gps, attitude=att, segments=[(0.0, seconds)])


@pytest.mark.parametrize("delay", [0.1, 0.2, 0.3])
def test_latency_found_on_a_manoeuvring_flight(delay):
    found, spread = latency(manoeuvring_log(delay))
    assert found == pytest.approx(delay, abs=0.03)
    assert spread == pytest.approx(1.4826 * 0.6745 * 0.05 * np.sqrt(2), rel=0.25)   # the fixes' noise, differenced


def test_latency_none_without_a_lag_or_the_streams():
    assert latency(manoeuvring_log(0.0))[0] is None
    log = manoeuvring_log(0.2)
    assert latency(dataclasses.replace(log, attitude=None)) == (None, None)
    short = dataclasses.replace(log, gps=log.gps.iloc[:20].reset_index(drop=True))
    assert latency(short) == (None, None)


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


def test_a_start_up_burst_of_stale_fixes_is_dropped_and_the_rest_restamped():
    """A receiver that buffered its first fixes hands them over at once, read within 40 ms of
    the first current one, seconds after their epochs (three Erle-Copter logs of the shared set
    begin so): those stamps fall after the next fix's epoch. They are dropped as stale; the log
    is not refused for them."""
    t, tow = jittered()
    tow[:4] = tow[4] - np.array([2.0, 1.8, 1.6, 1.4])
    t[:4] = t[4] - np.array([0.04, 0.03, 0.02, 0.01])
    new, keep, note = fix_epochs(t, tow)
    assert not keep[:4].any() and keep[4:].all()
    assert "4 read more than" in note and "stale" in note
    assert np.allclose(np.diff(new[keep]), 0.2, atol=1e-5)


def test_fixes_without_a_time_of_week_are_stamped_at_the_epochs_their_stamps_show():
    """A log whose receiver gives no time of week (a telemetry log, a PX4 log before the receiver
    knew the time): its fixes are put on the receiver's grid from the stamps alone, as the live
    monitor does; ``epochs=False`` keeps the stamps."""
    from quadformer.logs.flightlog import gps_stream

    t, tow = jittered(n=300)
    n = len(t)
    raw = {"t": t, "lat": np.full(n, 47.0), "lon": np.full(n, 8.0), "alt": np.full(n, 400.0),
           "vel": np.zeros((n, 3))}
    notes: list[str] = []
    g = gps_stream(raw, (47.0, 8.0, 400.0), notes)
    steps = np.diff(g["t"].to_numpy()[60:])
    assert np.abs(steps - 0.2).max() < 0.01 < np.abs(np.diff(t[60:]) - 0.2).max()
    assert any("no usable GPS time of week" in x for x in notes)
    kept: list[str] = []
    assert np.array_equal(gps_stream(raw, (47.0, 8.0, 400.0), kept, epochs=False)["t"].to_numpy(), t)
    assert not any("epochs" in x for x in kept)
