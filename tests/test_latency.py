"""The receiver's latency estimated online from a link's samples (``estimator.latency``), as a
log's whole record gives it (``logs.receiver_clock.latency``)."""

from __future__ import annotations

import numpy as np
import pytest
from test_receiver_clock import manoeuvring_log

from quadformer.estimator.latency import LATENCY_GRID, LatencyEstimator, pick_latency
from quadformer.logs.receiver_clock import latency


def fed(log, est=None, air_from=0.0):
    """``est`` (a new ``LatencyEstimator`` by default) fed ``log``'s attitude, IMU and fixes in time
    order, as a link delivers them; the fixes before ``air_from`` s on the ground."""
    est = est or LatencyEstimator()
    events = [(t, 0, q) for t, q in zip(log.attitude.t, log.attitude[["qx", "qy", "qz", "qw"]].to_numpy())]
    events += [(t, 1, f) for t, f in zip(log.imu.t, log.imu[["ax", "ay", "az"]].to_numpy())]
    events += [(t, 2, v) for t, v in zip(log.gps.t, log.gps[["vx", "vy", "vz"]].to_numpy())]
    for t, kind, x in sorted(events, key=lambda e: (e[0], e[1])):
        if kind == 0:
            est.attitude(t, x)
        elif kind == 1:
            est.imu(t, x)
        else:
            est.fix(t, x, t >= air_from)
    return est


@pytest.mark.parametrize("delay", [0.1, 0.2, 0.3])
def test_online_latency_is_the_logs(delay):
    log = manoeuvring_log(delay)
    est = fed(log)
    assert est.intervals == len(log.gps) - 1
    assert est.estimate() == pytest.approx(delay, abs=0.03)
    assert est.estimate() == pytest.approx(latency(log)[0], abs=0.02)


def test_online_latency_needs_the_air_and_enough_intervals():
    log = manoeuvring_log(0.2, seconds=60.0)
    on_ground = fed(log, air_from=1e9)
    assert on_ground.intervals == 0 and on_ground.estimate() is None
    est = fed(log, LatencyEstimator(min_intervals=300))          # 294 intervals in a minute at 5 Hz
    assert est.intervals < 300 and est.estimate() is None
    assert fed(manoeuvring_log(0.0)).estimate() is None         # no lag: nothing narrows the spread
    bounded = fed(log, LatencyEstimator(min_intervals=50, max_intervals=100))
    assert bounded.intervals == 100 and bounded.estimate() == pytest.approx(0.2, abs=0.05)


def test_samples_without_an_attitude_or_with_nans_are_not_taken():
    est = LatencyEstimator()
    est.imu(0.0, [0.0, 0.0, 9.8])                    # no attitude yet: no IMU integration
    est.fix(0.0, [1.0, 0.0, 0.0], True)
    for k in range(1, 200):
        est.attitude(0.01 * k, [0.0, 0.0, 0.0, 1.0] if k != 60 else [np.nan] * 4)
        est.imu(0.01 * k, [np.nan, 0.0, 9.8] if k == 50 else [0.0, 0.0, 9.8])
    est.fix(1.0, [np.nan, 0.0, 0.0], True)
    est.fix(1.2, [0.0, 0.0, 0.0], True)
    est.fix(1.4, [0.0, 0.0, 0.0], True)
    assert est.intervals == 1


def test_pick_latency_and_bad_settings():
    s = 1.0 + 5.0 * (LATENCY_GRID - 0.2) ** 2         # 20% narrower at 0.2 s than at 0
    assert pick_latency(s) == pytest.approx(0.2, abs=0.005)
    assert pick_latency(np.ones(len(LATENCY_GRID))) is None
    with pytest.raises(ValueError, match="one finite spread"):
        pick_latency([1.0, 2.0])
    with pytest.raises(ValueError, match="min_intervals"):
        LatencyEstimator(min_intervals=10)


def test_a_link_that_sends_its_attitude_once_tells_nothing():
    """The project's simulated vehicle sends one ATTITUDE (the start's); the IMU cannot be turned
    to the world after it, so no interval is taken and no latency found."""
    import dataclasses

    log = manoeuvring_log(0.2)
    once = dataclasses.replace(log, attitude=log.attitude.iloc[:1].reset_index(drop=True))
    est = fed(once)
    assert est.intervals == 0 and est.estimate() is None


def test_the_monitor_finds_its_links_latency_and_goes_on_with_it():
    """A vehicle manoeuvring for 60 s, its 5 Hz fixes measured 0.2 s before they are sent, streamed
    over MAVLink on 127.0.0.1 to the monitor without a GPS delay setting: the monitor finds the
    latency in the air and a new segment fuses the fixes that long before their stamps; with the
    delay set to 0 it keeps the stamps."""
    import math

    from test_live import run_monitor

    from quadformer.detectors import pretrained
    from quadformer.estimator.filter_config import FilterConfig
    from quadformer.sender import SenderConfig, VehicleStreams

    log = manoeuvring_log(0.2, seconds=60.0)
    vel = log.gps[["vx", "vy", "vz"]].to_numpy()
    pos = np.concatenate([[np.zeros(3)], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * 0.2, axis=0)])
    imu = log.imu[["ax", "ay", "az", "gx", "gy", "gz"]].to_numpy()
    streams = VehicleStreams(imu_t=log.imu.t.to_numpy(), imu=imu, gps_t=log.gps.t.to_numpy(), gps_enu=pos,
                             gps_vel=vel, att_t=log.attitude.t.to_numpy(),
                             att=log.attitude[["qx", "qy", "qz", "qw"]].to_numpy())
    det = pretrained.load("magbaro-glr")
    sender = SenderConfig(armed=(0.0, math.inf), in_air=(0.5, math.inf))
    for delay in (None, 0.0):
        filt = FilterConfig.matching(det.calibration_["sim_config"], sensors="gps+imu", gps_delay_s=delay)
        fixes, summary, report, lines = run_monitor(det, streams, sender, filter=filt)
        assert report.lost == 0 and summary["errors"] == 0
        starts = [s["started"] for s in summary["segment_list"]]
        if delay is None:
            assert summary["gps_delay"]["s"] == pytest.approx(0.2, abs=0.05)
            assert summary["gps_delay"]["source"].startswith("estimated from the link")
            assert len(starts) == 2 and starts[1].startswith("receiver latency")
            assert any("gps: receiver latency" in line for line in lines)
            assert summary["filter"]["gps_delay_s"] == summary["gps_delay"]["s"]
        else:
            assert summary["gps_delay"] == {"s": 0.0, "source": "the filter's setting"} and starts == ["start"]
