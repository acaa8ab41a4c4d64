"""The receiver's capture signature and a receiver fault's erratic fix, on hand-made online steps:
a capture's alarm is spoofing whatever the autopilot calls its jump, an accuracy jump without the
fix moving against the IMU and a fix swinging both ways stay degraded."""

from __future__ import annotations

import numpy as np
import pytest

from quadformer.detectors.receiver_health import ErraticFix, ReceiverHealth
from quadformer.detectors.streams import ScoredStream
from quadformer.resilience.step import OnlineStep


# -- the capture signature ----------------------------------------------------------------

def _capture_step(reports: list[dict], row: dict, events: tuple[tuple[float, str], ...] = ()) -> list:
    """An online step labelled by a receiver health fed ``reports`` (t and fields), then one alarm
    at t = 20 s carrying the raw innovation ``row``, then the autopilot's ``events``."""
    health = ReceiverHealth()
    step = OnlineStep(ScoredStream(np.array([5.0]), np.array([True])), flight_ids=[0], health=health)
    for rep in reports:
        step.receiver(rep.pop("t"), **rep)
    step.update_columns(20.0, row)
    for t, kind in events:
        step.event(t, kind)
    step.finish()
    return [a for a in step.alerts if not np.isnan(a.score)]


def _steady(t1: float = 19.0, **last) -> list[dict]:
    reps = [{"t": t, "fix_type": 3, "satellites": 11, "eph": 1.6, "speed_acc": 0.3, "noise": 100}
            for t in np.arange(0.0, t1, 0.2)]
    reps.append({"t": t1 + 0.8, "fix_type": 3, "satellites": 11, "eph": 1.6, "speed_acc": 0.3, "noise": 100,
                 **last})
    return reps


MOVING = {"res_gps_r_px": 1.0, "res_gps_r_py": 0.5, "res_gps_r_vx": 3.5, "res_gps_r_vy": 1.0}
STILL = {"res_gps_r_px": 0.3, "res_gps_r_py": 0.1, "res_gps_r_vx": 0.2, "res_gps_r_vy": 0.1}


def test_satellites_and_noise_jumping_while_the_fix_runs_from_the_imu_is_a_capture():
    (a,) = _capture_step(_steady(satellites=5, noise=139, eph=6.0, speed_acc=4.2), MOVING)
    assert a.kind == "spoofing" and a.reason.startswith("capture:")
    assert "satellites 5" in a.reason and "3.6 m/s against the IMU" in a.reason


def test_the_autopilot_calling_a_captures_jump_a_glitch_leaves_it_spoofing():
    (a,) = _capture_step(_steady(satellites=5, noise=139), MOVING, events=((20.2, "gps_glitch"),))
    assert a.kind == "spoofing" and a.reason.startswith("capture:")
    steady = _steady(t1=19.0)[:-1] + [{"t": 19.0, "fix_type": 3, "satellites": 11, "eph": 1.6, "noise": 100}]
    (b,) = _capture_step(steady, MOVING, events=((20.2, "gps_glitch"),))       # no capture sign
    assert b.kind == "degraded" and b.reason == "autopilot GPS glitch 0.20 s after its raise"


def test_a_fix_swinging_both_ways_against_the_imu_is_a_receiver_fault_not_a_capture():
    """A receiver with a 3D fix whose solution runs 12 m/s one way and 8 m/s back within a second
    (the satellites dropping as a capture's do): the alarm is degraded, reason the erratic fix;
    the same capture with the fix moving one way stays spoofing."""
    health = ReceiverHealth()
    step = OnlineStep(ScoredStream(np.array([0.0, 0.0, 0.0, 5.0]), np.array([False, False, False, True])),
                      flight_ids=[0], health=health)
    for rep in _steady(satellites=5, noise=139):
        step.receiver(rep.pop("t"), **rep)
    for t, v in ((19.4, 12.0), (19.6, -8.0), (19.8, 2.0), (20.0, 3.5)):
        step.update_columns(t, {**MOVING, "res_gps_r_vx": v})
    step.finish()
    (a,) = [x for x in step.alerts if not np.isnan(x.score)]
    assert a.kind == "degraded" and a.reason.startswith("erratic fix: its velocity against the IMU swung +12.0 "
                                                         "and -8.0 m/s east within 2 s")
    (b,) = _capture_step(_steady(satellites=5, noise=139), MOVING)      # one way: the capture's
    assert b.kind == "spoofing"


def test_the_erratic_sign_needs_both_ways_within_its_window_and_stands_its_hold():
    for hold in (0.0, 20.0):
        e = ErraticFix(hold_s=hold)
        for t, v in ((0.0, 6.0), (1.0, 2.0), (2.5, -6.0)):              # 2.5 s apart: not within 2 s
            e.push(t, 0.0, v)
        assert e.reason(2.5) is None
        e.push(2.9, 0.0, 5.5)
        assert "north" in e.reason(2.9)
        e.push(3.0, np.nan, np.nan)                                     # a row without a raw innovation
        assert e.reason(3.0).startswith("erratic fix")                  # the swing still in the window
        e.push(5.0, 0.0, 0.5)                                           # the swing has left the window
        if hold == 0.0:
            assert e.reason(5.0) is None
        else:                                                           # the fault stands 20 s after
            assert e.reason(5.0).endswith("2.0 s ago") and e.reason(23.0) is not None
            assert e.reason(23.1) is None
    with pytest.raises(ValueError, match="positive"):
        ErraticFix(speed=0.0)
    with pytest.raises(ValueError, match="hold_s"):
        ErraticFix(hold_s=-1.0)


def test_an_inflated_accuracy_hides_nothing_even_with_the_lock_lost_for_a_moment():
    reps = _steady(speed_acc=4.2, eph=6.0)
    reps.insert(-1, {"t": 19.5, "fix_type": 1, "satellites": 5})      # lock lost 0.3 s before
    (a,) = _capture_step(reps, MOVING)
    assert a.kind == "spoofing" and "speed accuracy 4.2" in a.reason


def test_an_accuracy_jump_without_the_fix_moving_against_the_imu_stays_degraded():
    (a,) = _capture_step(_steady(eph=6.0), STILL)
    assert a.kind == "degraded" and a.reason.startswith("accuracy jump")


def test_a_receiver_missing_fixes_is_degraded():
    reps = _steady()
    reps[-1]["t"] = 19.9                                               # 1.1 s after the previous report
    (a,) = _capture_step(reps, STILL)
    assert a.kind == "degraded" and a.reason.startswith("fixes missed")


def _lost_lock_then(report_after: dict, row_after: dict) -> list:
    """A capture that begins with a lost lock: an alarm raised at 20.0 s while the receiver reports
    no fix, standing through 20.2 and 20.4 s, when the fix is back (``report_after`` at 20.1 and
    20.3 s) and the rows are ``row_after``; the alerts raised by the step (the receiver's own
    degraded episode left out)."""
    health = ReceiverHealth()
    step = OnlineStep(ScoredStream(np.full(3, 500.0), np.ones(3, bool)), flight_ids=[0], health=health)
    for rep in _steady(t1=19.0):
        step.receiver(rep.pop("t"), **rep)
    step.receiver(19.9, fix_type=1, satellites=4)
    step.update_columns(20.0, MOVING)
    for t in (20.1, 20.3):
        step.receiver(t, **{"fix_type": 3, "satellites": 11, "eph": 1.6, "speed_acc": 0.3, "noise": 100,
                            **report_after})
        step.update_columns(t + 0.1, row_after)
    step.finish()
    return [a for a in step.alerts if not np.isnan(a.score)]


def test_a_capture_that_began_with_a_lost_lock_turns_the_degraded_alert_into_spoofing():
    degraded, capture = _lost_lock_then({"satellites": 5, "noise": 139}, MOVING)
    assert degraded.kind == "degraded" and degraded.reason.startswith("fix lost")
    assert degraded.start_s == 20.0 and degraded.end_s == pytest.approx(20.2)
    assert capture.kind == "spoofing" and capture.reason.startswith("capture: satellites 5")
    assert capture.start_s == pytest.approx(20.2)   # when the evidence came, not the alarm's first step


def test_a_lost_lock_whose_fix_comes_back_agreeing_with_the_imu_stays_degraded():
    (a,) = _lost_lock_then({"satellites": 5, "noise": 139}, STILL)      # the signs, but no motion against the IMU
    assert a.kind == "degraded" and a.end_s is None
    (b,) = _lost_lock_then({}, MOVING)                                  # the motion, but no capture sign
    assert b.kind == "degraded"


# -- the physical floor ---------------------------------------------------------------------
