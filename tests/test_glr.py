"""The self-normalising step test (``glr``) on hand-made innovations: it sees a step that no
clean stretch makes, normalises itself to a noisier vehicle, cannot be taught by a transient in
its calibration, and streams what it scores offline; the physical floor of a log the project
writes (the capture signature: test_capture_typing.py)."""

from __future__ import annotations

import copy

import numpy as np
import pandas as pd
import pytest

from quadformer.detectors import make
from quadformer.detectors.flight_scales import warmup_widening
from quadformer.detectors.glr import INPUTS, StepGLR

RATE = 5.0     # Hz, the GPS steps of the hand-made flights (a real receiver's rate)


def flight(seed: int, seconds: float = 180.0, noise: float = 0.1, fid: int = 0, in_air: float | None = 1.0,
           vel_step: tuple[float, float] | None = None, pos_step: tuple[float, float] | None = None) -> pd.DataFrame:
    """GPS steps of one flight: white raw innovations (position 0.05 m, velocity ``noise`` m/s), a
    receiver hovering (fix at rest with 0.02 m of noise); ``vel_step`` (t, size): from t the
    velocity innovation steps by size and the filter absorbs it (decay over 1 s), as a consistent
    drift switched on at once does; ``pos_step`` (t, size): the fix jumps by size (a bias)."""
    rng = np.random.default_rng(seed)
    t = np.arange(1, int(seconds * RATE) + 1) / RATE
    n = len(t)
    r = {c: rng.normal(0.0, noise if "_v" in c else 0.05, n) for c in INPUTS[:6]}
    fix = {c: rng.normal(0.0, 0.02, n) for c in INPUTS[6:]}
    if vel_step is not None:
        t0, size = vel_step
        on = t >= t0
        r["res_gps_r_vx"] = r["res_gps_r_vx"] + np.where(on, size * np.exp(-(t - t0) / 1.0), 0.0)
    if pos_step is not None:
        t0, size = pos_step
        on = t >= t0
        fix["gps_pos_x"] = fix["gps_pos_x"] + np.where(on, size, 0.0)
        r["res_gps_r_px"] = r["res_gps_r_px"] + np.where(on, size * np.exp(-(t - t0) / 1.0), 0.0)
    out = pd.DataFrame({"flight_id": fid, "t": t, **r, **fix})
    if in_air is not None:
        out["in_air"] = in_air
    return out


@pytest.fixture(scope="module")
def fitted() -> StepGLR:
    train = pd.concat([flight(s, fid=s) for s in range(4)], ignore_index=True)
    return make("glr").fit(train)


def test_a_velocity_step_scores_far_above_any_clean_step(fitted):
    clean = [fitted.decision_function(flight(s, fid=s)).max() for s in range(10, 14)]
    drift = fitted.decision_function(flight(20, vel_step=(100.0, 1.0)))
    t = np.arange(1, len(drift) + 1) / RATE
    assert max(clean) < 16.0                                       # chi-square(2)/2-like tails of white noise
    onset = drift[(t >= 100.0) & (t < 101.0)]
    assert onset.max() > 5 * max(clean)                            # 1 m/s against 0.1 m/s of noise
    assert drift[t < 100.0].max() < 16.0


def test_a_position_jump_shows_in_the_receivers_own_consistency(fitted):
    det = fitted.set_params(groups=("consistency",))
    s = det.decision_function(flight(21, pos_step=(90.0, 2.0)))
    t = np.arange(1, len(s) + 1) / RATE
    assert s[(t >= 90.0) & (t < 90.5)].max() > 1000                # 2 m against 2 cm of receiver noise
    assert s[t < 90.0].max() < 16.0
    det.set_params(groups=("position", "velocity", "consistency"))


def test_a_moving_receivers_jittered_stamps_and_a_skipped_epoch_are_consistent():
    """A receiver flying at 3.4 m/s, its 5 Hz fixes stamped when read (10 to 90 ms late) and one
    epoch skipped: the stamps 0.34 s apart span two periods (a 0.06 s jitter difference), which
    the consistency snaps to 0.4 s; without the snap the fix reads as a 0.2 m jump."""
    rng = np.random.default_rng(5)
    epochs = np.arange(1, 301) * 0.2
    epochs = np.delete(epochs, 150)                            # the receiver skipped one epoch
    t = epochs + rng.uniform(0.01, 0.09, len(epochs))
    t[149], t[150] = epochs[149] + 0.09, epochs[150] + 0.03     # 0.34 s between two stamps
    fix = np.stack([3.4 * epochs, np.zeros_like(epochs), np.full_like(epochs, 3.4), np.zeros_like(epochs)], axis=1)
    from quadformer.detectors.glr import consistency
    c = np.abs(consistency(t, fix)[:, 0])
    # the period is the median of the stamps' intervals, within a few ms of 0.2 s: 3.4 m/s x those ms
    assert c[150] < 0.05 and c[50:].max() < 0.05                   # (after 50 intervals, whose median it is)
    assert np.abs(consistency(epochs, fix)[1:]).max() < 1e-9


def test_a_noisier_vehicle_normalises_itself_after_calib_min_s_in_the_air(fitted):
    noisy = flight(30, noise=0.5)                                  # 5 times the training velocity noise
    s = fitted.decision_function(noisy)
    t = noisy["t"].to_numpy()
    warm = t < fitted.calib_min_s + fitted.reference_s + max(fitted.windows)
    # before it has calibrated: the prior times adapt (the noisiest vehicle allowed); after: its own
    assert s[~warm].max() < 20.0
    # a vehicle never in the air never calibrates: its scale stays the prior's times adapt, so its
    # 5-times noise scores 25/100 of a calibrated flight's
    ground = fitted.decision_function(noisy.assign(in_air=0.0))
    assert np.all(ground[~warm] <= s[~warm] * (25.0 / 100.0) * 1.6 + 1e-9)


def test_the_warm_up_widening_shrinks_to_one_at_calib_min_s():
    windows, q = (0.2, 1.0, 4.0), 0.75
    w = [warmup_widening(a, windows, 20.0, q) for a in (2.0, 5.0, 10.0, 20.0, 60.0)]
    np.testing.assert_allclose(w[3], 1.0)
    np.testing.assert_allclose(w[4], 1.0)
    assert all(np.all(a > b) for a, b in zip(w[:3], w[1:4]))      # fewer seconds, wider
    assert np.all(np.diff(w[0]) > 0)                                # longer windows, wider
    # the robust std's relative standard error at q 0.75 is 0.914 / sqrt(n): three of them beyond
    # what 20 s give, n = seconds / (window + 0.2 s)
    n = lambda a, M: a / (M + 0.2)                                  # noqa: E731
    expect = 1 + 3 * 0.9136 * (1 / np.sqrt(n(2.0, 0.2)) - 1 / np.sqrt(n(20.0, 0.2)))
    assert abs(w[0][0] - expect) < 2e-3


def test_a_step_early_in_the_air_scores_a_few_times_less_not_a_hundred(fitted):
    """A velocity step 8 s after take-off: with the warm-up (the flight's own scales from 2 s in
    the air, widened) it scores within a factor of 3 of the same step after the calibration; with
    the noisiest vehicle's scales until 20 s (warm_s = calib_min_s, as before the warm-up) a
    hundredth. The clean warm-up of a vehicle five times noisier than trained stays quiet, and so
    does a calm hover's before its first manoeuvre."""
    early = flight(60, vel_step=(8.0, 1.0))
    late = flight(60, vel_step=(120.0, 1.0))
    t = early["t"].to_numpy()
    on_early, on_late = (t >= 8.0) & (t < 10.0), (t >= 120.0) & (t < 122.0)
    s_early = fitted.decision_function(early)[on_early].max()
    s_late = fitted.decision_function(late)[on_late].max()
    old = copy.deepcopy(fitted).set_params(warm_s=fitted.calib_min_s)
    s_old = old.decision_function(early)[on_early].max()
    assert s_early > s_late / 3
    assert s_old < s_late / 30
    noisy = flight(61, seconds=30.0, noise=0.5)
    assert fitted.decision_function(noisy)[noisy["t"].to_numpy() < 20.0].max() < 16.0
    # a calm hover (a fifth of the trained noise) until the first manoeuvre at 6 s (the trained
    # noise): the warm-up never takes a scale below the prior, so the manoeuvre scores as a clean
    # step, not 25 times one
    calm = flight(62, seconds=30.0)
    quiet = calm["t"].to_numpy() < 6.0
    for c in INPUTS[:6]:
        calm.loc[quiet, c] = calm.loc[quiet, c] / 5.0
    assert fitted.decision_function(calm).max() < 16.0


def test_a_resumed_stream_keeps_the_flights_calibration(fitted):
    """The live monitor restarting its filter in the air: the new stream takes the scales the
    flight had calibrated as its prior, from its first step (not the trained ones times adapt),
    and a flight not yet calibrated starts afresh."""
    rows = flight(41, noise=0.3).to_dict("records")
    before, early = fitted.stream(1), fitted.stream(1)
    for k, row in enumerate(rows[:200]):                          # 40 s in the air
        before.update(row)
        if k < 50:                                                # 10 s: still warming up
            early.update(row)
    assert before.cal[0].calibrated is not None and early.cal[0].calibrated is None
    own = before.cal[0].scale.copy()
    assert not np.allclose(own, fitted.scale_)                    # three times the trained noise
    after, fresh = fitted.stream(1), fitted.stream(1)
    after.resume(before)
    fresh.resume(early)
    after.update(rows[200])
    fresh.update(rows[200])
    np.testing.assert_array_equal(after.cal[0].scales(rows[200]["t"]), own)
    np.testing.assert_array_equal(fresh.cal[0].scale, fitted.scale_ * fitted.adapt)
    with pytest.raises(ValueError, match="same flights"):
        fitted.stream(2).resume(before)


def test_a_transient_in_the_calibration_window_does_not_teach_the_scale(fitted):
    quiet = flight(40)
    spoofed = flight(40, vel_step=(30.0, 3.0))                     # a 3 m/s onset inside the first 60 s
    a, b = fitted.stream(1), fitted.stream(1)
    for row_a, row_b in zip(quiet.to_dict("records"), spoofed.to_dict("records")):
        a.update(row_a)
        b.update(row_b)
    sa, sb = a.cal[0].scale, b.cal[0].scale
    # the onset's steps are not learned from: the scales differ by the quantiles' sampling noise
    # over the few hundred steps of the window only (measured: within 16%)
    assert np.allclose(sa, sb, rtol=0.2)
    # and no flight teaches a scale beyond adapt times the prior, either way
    assert np.all(sb <= fitted.scale_ * fitted.adapt * (1 + 1e-12))
    assert np.all(sb >= fitted.scale_ / fitted.adapt * (1 - 1e-12))


def test_the_stream_with_time_and_in_air_equals_offline(fitted):
    rows = pd.concat([flight(50, in_air=None).assign(in_air=0.0).iloc[:100],
                      flight(51, vel_step=(80.0, 0.8), in_air=None).assign(in_air=1.0).iloc[100:]], ignore_index=True)
    rows["t"] = np.arange(1, len(rows) + 1) / RATE
    offline = fitted.decision_function(rows)
    st = fitted.stream(1)
    online = np.array([st.update(r).score[0] for r in rows.to_dict("records")])
    np.testing.assert_allclose(online, offline, rtol=1e-9, atol=1e-9)


def test_bad_settings_and_input_are_named(fitted):
    with pytest.raises(ValueError, match="groups"):
        make("glr", groups=("altitude",)).fit(flight(1))
    with pytest.raises(ValueError, match="adapt"):
        make("glr", adapt=0.5).fit(flight(1))
    with pytest.raises(ValueError, match="windows"):
        make("glr", windows=(0.2, -1.0)).fit(flight(1))
    with pytest.raises(ValueError, match="warm_s"):
        make("glr", warm_s=30.0).fit(flight(1))
    st = fitted.stream(1)
    row = flight(2).iloc[5].to_dict()
    st.update(row)
    with pytest.raises(ValueError, match="time went back"):
        st.update({**row, "t": row["t"] - 1.0})
    bad = flight(3)
    bad.loc[7, "res_gps_r_vx"] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        fitted.decision_function(bad)


def test_the_floor_of_a_log_the_project_writes(tmp_path):
    from quadformer.logs import read_log
    from quadformer.logs.noise import detection_floor

    log = read_log("tests/fixtures/logs/sim_copter.bin")
    f1 = detection_floor(log, per_hour=1.0)
    f100 = detection_floor(log, per_hour=100.0)
    assert f1 is not None and f1.intervals > 100
    assert 0 < f100.offset_m < f1.offset_m and 0 < f100.drift_ms < f1.drift_ms   # a laxer budget sees less
    # one interval's chi-square test at 1 alarm per hour: about 5.6 standard deviations
    assert f1.drift_ms / f1.sigma_vel_ms == pytest.approx(5.6, abs=0.4)
    assert detection_floor(log.__class__(**{**log.__dict__, "attitude": None})) is None
    # the simulator's noise is Gaussian: the floors with the log's own tails are near the Gaussian's
    assert f1.drift_ms <= f1.drift_tail_ms <= 1.5 * f1.drift_ms


def test_a_heavier_tail_raises_the_floor():
    from quadformer.logs.noise import tail_floor

    rng = np.random.default_rng(7)
    gauss, dof = tail_floor(rng.standard_normal((1500, 2)), 1.0, 5.0)
    assert gauss == pytest.approx(5.6, abs=0.4) and dof > 20          # a chi-square test's 5.6 std
    heavy = rng.standard_normal((1500, 2)) / np.sqrt(rng.chisquare(5, 1500) / 5)[:, None]
    floor, dof = tail_floor(heavy / np.median(np.abs(heavy)) * 0.6745, 1.0, 5.0)
    assert 3.5 <= dof <= 8 and floor > 2 * gauss                       # Student-t, 5 dof
    assert all(np.isnan(tail_floor(rng.standard_normal((10, 2)), 1.0, 5.0)))   # too few intervals


# -- vehicle profiles -----------------------------------------------------------------------

FIX = "tests/fixtures/logs"


@pytest.fixture(scope="module")
def sim_glr(bias_dataset):
    return make("glr").fit(bias_dataset.flights).calibrate(40.0, 40.0)


def test_a_profile_on_few_minutes_keeps_the_threshold_and_says_what_it_needs(sim_glr, tmp_path):
    from quadformer.logs.calibration import vehicle_profile

    det = copy.deepcopy(sim_glr)
    prof = vehicle_profile(det, [f"{FIX}/sim_copter.bin", f"{FIX}/copter_armed_only.bin"], per_hour=1.0)
    assert prof.minutes < 3.0 and not prof.scales_set and not prof.narrowed
    assert prof.threshold >= prof.shipped_threshold                 # never narrowed on so little
    assert "needs 180" in prof.message and "noise scales not set" in prof.message
    assert prof.sensors == "gps+imu+mag+baro" and prof.identity["autopilot"] == "ArduPilot"
    path = prof.detector.save(tmp_path / "vehicle.qfm")
    from quadformer.detectors import load
    again = load(path)
    assert again.calibration_["vehicle_needed_minutes"] == 180.0 and again.threshold_ == prof.threshold
    # the fixture logs state no GPS delay and fly a smooth circle: no latency to estimate, none recorded
    assert again.calibration_["vehicle_gps_delay_s"] is None and "receiver latency" not in prof.message


def test_a_profile_refuses_another_vehicles_log_and_another_sensor_set(sim_glr, tmp_path):
    from quadformer.logs import LogError, read_log
    from quadformer.logs.calibration import vehicle_profile
    from quadformer.logs.detect import NothingToScore, detect_log
    from quadformer.logs.vehicle import check_profile

    prof = vehicle_profile(copy.deepcopy(sim_glr), [f"{FIX}/sim_copter.bin", f"{FIX}/copter_armed_only.bin"])
    det = prof.detector
    px4 = read_log(f"{FIX}/sample_log_small.ulg")
    with pytest.raises(LogError, match="ArduPilot vehicle; this log is PX4"):
        check_profile(det, px4, "gps+imu+mag+baro")
    with pytest.raises(NothingToScore, match="fusing gps\\+imu\\+mag\\+baro; this log fuses gps\\+imu"):
        detect_log(f"{FIX}/copter_core_switch.bin", det)            # the same autopilot, no compass nor barometer
    res = detect_log(f"{FIX}/sim_copter.bin", det)                  # its own: scored
    assert len(res.scores) > 100


def test_a_vehicle_of_its_own_noise_gets_its_scales_from_enough_minutes(sim_glr):
    """With the vehicle's scales, a profile uses them from take-off: no warm-up (the prior times
    adapt for the first 2 s in the air, then the flight's own scales widened for their few seconds)."""

    det = copy.deepcopy(sim_glr)
    det.vehicle_ = True
    s_vehicle = det.decision_function(flight(60, noise=0.1))
    s_prior = sim_glr.decision_function(flight(60, noise=0.1))
    no_warm_up = copy.deepcopy(sim_glr).set_params(warm_s=sim_glr.calib_min_s)
    s_adapt = no_warm_up.decision_function(flight(60, noise=0.1))
    t = np.arange(1, len(s_vehicle) + 1) / RATE
    early = (t > 8.0) & (t < 20.0)
    assert s_vehicle[early].mean() > 1.5 * s_prior[early].mean()    # the warm-up's widening
    assert s_vehicle[early].mean() > 10 * s_adapt[early].mean()     # the prior x adapt until calibrated
