"""Alerts labelled by where the vehicle was (ground, take-off transition, air) and by what they
are (spoofing, or a degraded receiver): the flight phase and the receiver health online, the
online step that labels its alerts with them, and offline detection through the same step."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from quadformer import make
from quadformer.detectors import alert_counts, alerts_frame
from quadformer.detectors.alarms import ALERT_COLUMNS, Alert, onset_flags
from quadformer.detectors.flight_phase import FlightPhase, PhaseRule, phases
from quadformer.detectors.receiver_health import HealthRule, ReceiverHealth
from quadformer.detectors.streams import ScoredStream
from quadformer.logs.detect import step_alerts
from quadformer.resilience.step import OnlineStep

RATE = 5          # Hz, the receiver's reports and the GPS steps of the hand-made flights


def times(t0: float, t1: float) -> np.ndarray:
    """Steps at RATE from t0 to t1 (excluded), exact multiples of 1/RATE."""
    return np.arange(round(t0 * RATE), round(t1 * RATE)) / RATE


# -- flight phase ------------------------------------------------------------------------

def test_phase_from_the_vehicles_events():
    fp = FlightPhase()
    assert fp.source == "none" and fp.update(0.0) == "air"          # nothing known: never labelled away
    fp.event(1.0, "armed")
    assert fp.source == "events" and fp.update(2.0) == "ground"     # armed, not yet taken off
    fp.event(3.0, "mode_change")                                    # not a phase event: ignored
    fp.event(10.0, "takeoff")
    assert [fp.update(t) for t in (10.0, 12.0, 14.9, 15.0, 30.0)] == [
        "transition", "transition", "transition", "air", "air"]     # settle_s = 5 s
    fp.event(40.0, "landed")
    assert fp.update(40.0) == "ground" and fp.update(45.0) == "ground"
    fp.event(50.0, "takeoff")
    assert fp.update(52.0) == "transition" and fp.update(56.0) == "air"
    fp.event(60.0, "disarmed")
    assert fp.update(60.0) == "ground" and fp.source == "events"
    # disarmed: on the ground, whatever else is unknown; a longer settle from the rule
    grounded = FlightPhase()
    grounded.event(0.0, "disarmed")
    assert grounded.update(1.0) == "ground"
    slow = FlightPhase(PhaseRule(settle_s=8.0))
    slow.event(0.0, "takeoff")
    assert slow.update(7.9) == "transition" and slow.update(8.0) == "air"


def test_phase_from_height_climb_hold_and_disarm():
    """Height on a barometer's datum (about 100 m): the ground is the height at arming; a climb
    of more than climb_m while armed takes off, land_hold_s within climb_m / 2 lands."""
    t = times(0, 70)
    h = np.full(len(t), 100.0)
    h[t < 1.5] = 95.0                                   # carried up 5 m before arming: not a take-off
    climb = (t >= 10) & (t < 20)
    h[climb] = 100.0 + (t[climb] - 10.0)                # 1 m/s: more than 1 m up after 11 s
    h[(t >= 20) & (t < 40)] = 110.0
    down = (t >= 40) & (t < 50)
    h[down] = 110.0 - (t[down] - 40.0)
    h[t >= 50] = 100.3                                  # landed 0.3 m above the arming height
    events = pd.DataFrame({"t": [0.0, 2.0], "event": ["disarmed", "armed"], "detail": ["", ""]})
    height = pd.DataFrame({"t": t, "h": h})
    got = phases(t, events, height)
    takeoff = t[np.argmax(h - 100.0 > 1.0)]
    assert takeoff == pytest.approx(11.2)               # the first sample more than 1 m up
    expect = np.where(t < takeoff, "ground", np.where(t - takeoff < 5.0, "transition", "air"))
    low = t[np.argmax((t > 40) & (h <= 100.5))]         # the first sample within 0.5 m on the way down
    expect[t - low >= 3.0] = "ground"                   # land_hold_s later
    expect[(t >= low - 10.0) & (expect == "air")] = "transition"   # the landing's land_s, up to its hold's end
    assert low == pytest.approx(49.6)
    assert list(got) == list(expect)
    fp = FlightPhase()
    fp.update(0.0, 50.0)
    assert fp.source == "height" and fp.ground_h == 50.0      # no arming seen: the first height
    # disarming grounds at once; a disarmed vehicle lifted is not flying
    fp = FlightPhase()
    fp.event(0.0, "armed")
    fp.update(0.0, 20.0)
    assert fp.update(1.0, 23.0) == "transition"
    fp.event(2.0, "disarmed")
    assert fp.update(2.0, 23.0) == "ground" and fp.update(3.0, 25.0) == "ground"
    # a take-off event overrides the height from then on
    fp.event(4.0, "takeoff")
    assert fp.update(20.0, 20.0) == "air" and fp.source == "events"


def test_phase_without_events_or_height_is_air():
    assert list(phases(times(0, 3))) == ["air"] * 15
    with pytest.raises(ValueError, match="climb_m"):
        PhaseRule(climb_m=0.0)
    with pytest.raises(ValueError, match="in order"):
        phases([2.0, 1.0])


# -- receiver health ---------------------------------------------------------------------

def feed(health: ReceiverHealth, t: np.ndarray, **columns) -> list:
    """Every report of a hand-made receiver to ``health``; the alert events, in order."""
    events = []
    for k, tk in enumerate(t):
        events += health.report(tk, **{c: float(np.broadcast_to(v, t.shape)[k]) for c, v in columns.items()})
    return events


def test_fix_loss_raises_a_degraded_alert_at_the_first_report_without_a_fix():
    h = ReceiverHealth()
    t = times(0, 15)
    fix = np.where((t >= 4.0) & (t < 6.0), 1, 3)
    ev = []
    for k, tk in enumerate(t):
        out = h.report(tk, fix[k], satellites=12, eph=1.0)
        if tk == 4.0:
            assert [e.event for e in out] == ["alert_start"]            # raised by the report that shows it
            assert h.degraded(4.0) == "fix lost (fix type 1)"
        ev += [(tk, e) for e in out]
    assert [(tk, e.event) for tk, e in ev] == [(4.0, "alert_start"), (9.0, "alert_end")]
    (a,) = h.alerts
    assert (a.start_s, a.end_s, a.kind, a.attack_type, a.reason) == (4.0, 9.0, "degraded", "none",
                                                                     "fix lost (fix type 1)")
    assert math.isnan(a.score) and a.phase == "air"
    assert h.degraded(8.9) is not None and h.degraded(9.0) is None    # hold_s = 3 s after the fix returns


def test_acquiring_the_first_fix_is_not_a_fix_loss():
    """A receiver without a fix from power-up is acquiring, not degraded; a loss after its first
    fix is (a real log's receiver reports fix type 0 for its first second on the ground)."""
    h = ReceiverHealth()
    t = times(0, 10)
    fix = np.where(t < 2.0, 0, np.where((t >= 6.0) & (t < 7.0), 0, 3))
    for k, tk in enumerate(t):
        h.report(tk, fix[k], eph=np.nan if fix[k] == 0 else 1.0)
        assert (h.degraded(tk) is not None) == (tk >= 6.0)
    h.finish()
    assert [a.start_s for a in h.alerts] == [6.0]


def test_accuracy_jump_and_autopilot_glitch_are_degradation():
    rng = np.random.default_rng(4)
    t = times(0, 30)
    eph = 1.0 + 0.1 * rng.standard_normal(len(t))
    eph[(t >= 20.0) & (t < 21.0)] = 7.0
    h = ReceiverHealth()
    ev = feed(h, t, fix_type=3, eph=eph)
    assert [e.event for e in ev] == ["alert_start", "alert_end"]
    (a,) = h.alerts
    assert a.start_s == 20.0 and a.end_s == 24.0                        # the next report at 21 s, + 3 s
    assert a.reason.startswith("accuracy jump (eph 7.0 m, median 1.0 m")
    # a jump below the floor is no sign: 0.1 m to 0.9 m
    quiet = ReceiverHealth()
    assert feed(quiet, t, fix_type=3, eph=np.where(t < 20, 0.1, 0.9)) == [] and quiet.alerts == []
    # the autopilot's glitch: a sign from its event until it is cleared
    g = ReceiverHealth()
    ev = g.event(10.0, "gps_glitch", phase="ground")
    assert [e.event for e in ev] == ["alert_start"] and ev[0].alert.phase == "ground"
    assert feed(g, times(10.2, 15.0), fix_type=3, eph=1.0) == []
    assert g.degraded(14.9) == "autopilot GPS glitch"
    assert g.event(15.0, "gps_glitch_cleared") == []
    assert g.degraded(17.9) == "autopilot GPS glitch" and g.tick(17.9) == []
    (end,) = g.tick(18.0)
    assert end.event == "alert_end" and end.alert.end_s == 18.0 and g.degraded(18.0) is None
    with pytest.raises(ValueError, match="eph_ratio"):
        HealthRule(eph_ratio=1.0)


def spoof_like() -> pd.DataFrame:
    """A spoofer's capture: satellites 14 -> 6, noise floor doubled, jamming indicator up from
    10 s, while the receiver keeps its 3D fix and a steady accuracy."""
    t = times(0, 30)
    on = t >= 10.0
    return pd.DataFrame({"t": t, "fix_type": 3, "satellites": np.where(on, 6, 14), "eph": 0.9, "epv": 1.4,
                         "speed_acc": 0.3, "jamming": np.where(on, 120, 20), "noise": np.where(on, 160, 80),
                         "spoofing": 1})


def test_a_spoof_is_not_degradation_so_its_alarm_stays_spoofing():
    rep = spoof_like()
    h = ReceiverHealth()
    assert feed(h, rep.t.to_numpy(), **{c: rep[c].to_numpy() for c in rep.columns if c != "t"}) == []
    assert all(h.degraded(t) is None for t in rep.t) and not h.spoof_flag(29.8)
    alerts = drive(rep, alarm_at=[(12.0, 14.0)])
    assert [(a.kind, a.reason, a.start_s, a.end_s) for a in alerts] == [("spoofing", None, 12.0, 14.0)]


def test_the_receivers_spoofing_flag_raises_a_spoofing_alert_without_an_alarm():
    rep = spoof_like().assign(spoofing=lambda f: np.where((f.t >= 5.0) & (f.t < 8.0), 2, 1))
    (a,) = drive(rep, alarm_at=[])
    assert (a.kind, a.reason, a.start_s, a.end_s) == ("spoofing", "receiver reports spoofing", 5.0, 8.0)


# -- the online step ---------------------------------------------------------------------

def drive(receiver: pd.DataFrame | None, alarm_at, events: list[tuple[float, str]] = (), t_end: float = 30.0,
          phase: FlightPhase | None = None) -> list[Alert]:
    """An OnlineStep over a ScoredStream (alarmed in the [start, end) spans of ``alarm_at``),
    fed the receiver's reports and the events due before each GPS step by hand."""
    t = times(0, t_end)
    alarm = np.zeros(len(t), dtype=bool)
    for s, e in alarm_at:
        alarm |= (t >= s) & (t < e)
    score = np.where(alarm, 50.0, 1.0)
    step = OnlineStep(ScoredStream(score, alarm), flight_ids=["f"], phase=phase or FlightPhase(),
                      health=ReceiverHealth(flight_id="f"))
    items = sorted([(te, 0, kind) for te, kind in events]
                   + ([] if receiver is None else [(r["t"], 1, r) for r in receiver.to_dict("records")]),
                   key=lambda x: x[:2])
    k = 0
    for tk in t:
        while k < len(items) and items[k][0] <= tk:
            te, src, what = items[k]
            if src == 0:
                step.event(te, what)
            else:
                step.receiver(te, **{c: v for c, v in what.items() if c != "t"})
            k += 1
        step.update_columns(tk, {})
    step.finish()
    return step.alerts


def test_the_online_step_labels_alarms_by_flight_phase_and_receiver_health():
    ev = [(0.0, "armed"), (10.0, "takeoff"), (40.0, "landed")]
    alerts = drive(None, alarm_at=[(3.0, 4.0), (12.0, 13.0), (20.0, 21.0), (41.0, 42.0)], events=ev, t_end=45.0)
    assert [(a.start_s, a.phase, a.kind) for a in alerts] == [
        (3.0, "ground", "spoofing"), (12.0, "transition", "spoofing"), (20.0, "air", "spoofing"),
        (41.0, "ground", "spoofing")]
    # an alarm raised while the fix is lost is a degraded receiver's, next to the receiver's own alert
    rep = spoof_like().assign(spoofing=1, satellites=12, jamming=20, noise=80,
                              fix_type=lambda f: np.where((f.t >= 15.0) & (f.t < 16.0), 1, 3))
    alerts = drive(rep, alarm_at=[(15.2, 17.0), (25.0, 26.0)], events=ev)
    assert [(a.start_s, a.end_s, a.kind, a.attack_type, a.phase, a.reason) for a in alerts] == [
        (15.0, 19.0, "degraded", "none", "air", "fix lost (fix type 1)"),
        (15.2, 17.0, "degraded", "attack", "air", "fix lost (fix type 1)"),
        (25.0, 26.0, "spoofing", "attack", "air", None)]
    counts = alert_counts(alerts)
    assert counts == {"alerts": 1, "alerts_ground": 0, "alerts_transition": 0, "alerts_degraded": 2,
                      "alerts_total": 3}
    frame = alerts_frame(alerts)
    assert list(frame.columns) == ALERT_COLUMNS and list(frame.kind) == ["degraded", "degraded", "spoofing"]
    assert "degraded alert at 15.0 s in the air" in str(alerts[0]) and "fix lost" in str(alerts[0])
    with pytest.raises(ValueError, match="one flight"):
        OnlineStep(n=2, phase=FlightPhase())
    with pytest.raises(ValueError, match="flight_id"):
        OnlineStep(n=1, flight_ids=["a"], health=ReceiverHealth(flight_id="b"))


def test_an_alarm_the_autopilot_calls_a_glitch_a_moment_later_is_degraded():
    """The autopilot's glitch test and the detector see the same fix: an alarm raised 0.2 s before
    its glitch report is the degraded episode's, as one raised after the report is; one raised
    1 s before it stays spoofing (a spoof the autopilot then also sees)."""
    ev = [(0.0, "armed"), (5.0, "takeoff"), (20.2, "gps_glitch"), (23.0, "gps_glitch_cleared"),
          (27.0, "gps_failsafe")]
    alerts = drive(None, alarm_at=[(20.0, 21.0), (26.0, 27.5)], events=ev)
    assert [(a.start_s, a.kind, a.reason) for a in alerts] == [
        (20.0, "degraded", "autopilot GPS glitch 0.20 s after its raise"),
        (20.2, "degraded", "autopilot GPS glitch"),
        (26.0, "spoofing", None),
        (27.0, "degraded", "autopilot GPS failsafe")]
    assert alert_counts(alerts)["alerts"] == 1 and alert_counts(alerts)["alerts_degraded"] == 3
    # (a capture's alarm keeps its kind: test_glr's capture tests)


def test_the_monitor_writes_a_glitch_relabel_and_counts_the_alert_degraded(tmp_path):
    import json

    from quadformer.live.actions import Records
    from quadformer.live.alerts import Alerting
    from quadformer.live.config import MonitorConfig
    from quadformer.resilience.admission import FUSING

    t = times(0, 25)
    alarm = (t >= 20.0) & (t < 21.0)
    score = np.where(alarm, 50.0, 1.0)
    det = make("chi2").fit(pd.DataFrame({"flight_id": 0, "t": t, "res_gps_nis": score}))
    det.calibrate(40.0)
    step = OnlineStep(ScoredStream(score, alarm), flight_ids=[0], phase=FlightPhase(),
                      health=ReceiverHealth(flight_id=0))
    lines, records = [], Records(tmp_path)
    alerting = Alerting(det, MonitorConfig(connect="udpin:127.0.0.1:0"), lines.append, lambda e: None)
    alerting.attach(None, records)
    events = {0.0: "armed", 5.0: "takeoff", 20.2: "gps_glitch"}
    for tk in t:
        if tk in events:
            alerting.events(step.event(tk, events[tk]), 0, math.nan, FUSING)
        out = step.update_columns(tk, {})
        alerting.events(out.events, 0, float(out.score[0]), FUSING)
    alerting.events(step.finish(), 0, math.nan, FUSING)
    records.close()
    on_disk = [json.loads(x) for x in (tmp_path / "alerts.jsonl").read_text().splitlines()]
    (relabel,) = [e for e in on_disk if e["event"] == "alert_relabel"]
    assert (relabel["start_s"], relabel["kind"], relabel["was_kind"], relabel["phase"]) == (
        20.0, "degraded", "spoofing", "air")
    assert {k: v for k, v in alerting.counts.items() if v} == {"alerts_degraded": 2, "alerts_total": 2}
    assert any("alert of t 20.0 s: degraded, not spoofing (autopilot GPS glitch 0.20 s" in x for x in lines)


# -- offline: step_alerts ----------------------------------------------------------------

def log_table(seed: int = 2) -> tuple[pd.DataFrame, object, np.ndarray]:
    """Two segments of a hand-made log (0-30 s and 40-70 s at 5 Hz), chi-square NIS with
    spikes at 6 s (on the ground), 21 s and 55 s; a chi2 gate fit and calibrated on them."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([times(0, 30), times(40, 70)])
    nis = rng.chisquare(6, len(t))
    for s in (6.0, 21.0, 55.0):
        nis[(t >= s) & (t < s + 1.0)] += 200.0
    rows = pd.DataFrame({"flight_id": np.where(t < 35, 0, 1).astype(np.int32), "t": t, "res_gps_nis": nis})
    det = make("chi2").fit(rows)
    det.calibrate(60.0)
    return rows, det, det.decision_function(rows)


def log_streams() -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """The vehicle's events, the receiver's reports (fix lost 33-34 s, between the segments, and
    at 60-61 s) and a barometer's height."""
    events = pd.DataFrame({"t": [1.0, 10.0, 25.0, 35.0, 68.0], "event": ["armed", "takeoff", "gps_glitch",
                                                                        "gps_glitch_cleared", "landed"],
                           "detail": ""})
    t = times(0, 72)
    fix = np.where(((t >= 33) & (t < 34)) | ((t >= 60) & (t < 61)), 0, 3)
    receiver = pd.DataFrame({"t": t, "fix_type": fix, "satellites": 12.0, "eph": 1.0, "epv": 1.5,
                             "speed_acc": 0.3, "jamming": np.nan, "noise": 80.0, "spoofing": np.nan})
    height = pd.DataFrame({"t": t, "h": np.where((t > 10) & (t < 68), 30.0, 0.0)})
    return events, receiver, height


def test_step_alerts_with_events_and_receiver_equal_the_online_step_driven_by_hand():
    rows, det, scores = log_table()
    events, receiver, height = log_streams()
    one = rows[rows.flight_id == 0].reset_index(drop=True)
    got = step_alerts(one, scores[: len(one)], det, "shape", events=events, receiver=receiver, height=height)
    alarms = scores[: len(one)] > det.threshold_
    above = onset_flags(one, det)
    step = OnlineStep(ScoredStream(scores[: len(one)], alarms, None, above), flight_ids=[0], phase=FlightPhase(),
                      health=ReceiverHealth(flight_id=0))
    items = sorted([(r.t, 0, r) for r in events.itertuples()] + [(r.t, 1, r) for r in receiver.itertuples()]
                   + [(r.t, 2, r) for r in height.itertuples()], key=lambda x: x[:2])
    k = 0
    for tk in one.t:
        while k < len(items) and items[k][0] <= tk:
            te, src, r = items[k]
            if src == 0:
                step.event(te, r.event)
            elif src == 1:
                step.receiver(te, fix_type=r.fix_type, satellites=r.satellites, eph=r.eph, epv=r.epv,
                              speed_acc=r.speed_acc, jamming=r.jamming, noise=r.noise, spoofing=r.spoofing)
            else:
                step.height(te, r.h)
            k += 1
        step.update_columns(tk, {})
    for te, src, r in items[k:]:
        if src == 0:
            step.event(te, r.event)
        elif src == 1:
            step.receiver(te, fix_type=r.fix_type, eph=r.eph)
        else:
            step.height(te, r.h)
    step.finish()
    assert got == step.alerts
    assert [(a.start_s, a.kind, a.phase, a.reason) for a in got] == [
        (6.0, "spoofing", "ground", None), (21.0, "spoofing", "air", None),
        (25.0, "degraded", "air", "autopilot GPS glitch"),      # the glitch and the fix lost at 33 s: one episode
        (60.0, "degraded", "transition",                        # after the last row: fed before the finish,
         "fix lost (fix type 0); landing at t=68.0 s (landed event)")]   # and within 10 s before the landing
    # without events, receiver or height: the alerts of the batch tracker, spoofing in the air
    plain = step_alerts(rows, scores, det, "shape")
    assert [(a.start_s, a.kind, a.phase, a.reason) for a in plain] == [
        (6.0, "spoofing", "air", None), (21.0, "spoofing", "air", None), (55.0, "spoofing", "air", None)]


def test_step_alerts_over_segments_raise_each_episode_once_and_keep_the_phase():
    rows, det, scores = log_table()
    events, receiver, height = log_streams()
    alerts = step_alerts(rows, scores, det, "shape", events=events, receiver=receiver, height=height)
    assert [(a.flight_id, a.start_s, a.end_s, a.kind, a.phase) for a in alerts] == [
        (0, 6.0, 7.0, "spoofing", "ground"), (0, 21.0, 22.0, "spoofing", "air"),
        (0, 25.0, 38.0, "degraded", "air"),                 # the glitch, then the fix lost between segments
        (1, 55.0, 56.0, "spoofing", "air"),                 # the take-off in segment 0 still holds
        (1, 60.0, 64.0, "degraded", "transition")]          # within 10 s before the landing at 68 s
    # a receiver's degradation comes out without any alarm of the detector
    quiet = scores.copy()
    quiet[quiet > det.threshold_] = 0.0
    degraded = step_alerts(rows, quiet, det, "shape", receiver=receiver)
    assert [(a.flight_id, a.start_s, a.kind) for a in degraded] == [(0, 33.0, "degraded"), (1, 60.0, "degraded")]
    assert step_alerts(rows, quiet, det, "shape") == []
    with pytest.raises(ValueError, match="fix_type"):
        step_alerts(rows, scores, det, "shape", receiver=receiver.drop(columns="fix_type"))
