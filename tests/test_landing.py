"""The seconds before a landing are a transition, as those after a take-off are, and a crash is not
spoofing: the landing from the vehicle's events, the height or an impact in the IMU; the alerts
raised in the air before it relabelled online when it is seen, equal to offline detection
(``step_alerts``) and to the whole-log phases (``phases``). Hand-made flights, small."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from quadformer import make
from quadformer.detectors import alert_counts
from quadformer.detectors.alarms import onset_flags
from quadformer.detectors.flight_phase import FlightPhase, PhaseRule, phases
from quadformer.detectors.impact import G0, ImpactDetector, ImpactRule, impacts
from quadformer.detectors.receiver_health import ReceiverHealth
from quadformer.detectors.streams import ScoredStream
from quadformer.live.actions import Records
from quadformer.live.alerts import Alerting, statustext
from quadformer.live.config import MonitorConfig
from quadformer.live.flight_state import FlightState
from quadformer.logs.detect import step_alerts
from quadformer.resilience.admission import FUSING
from quadformer.resilience.step import OnlineStep
from quadformer.sensors import mavlink as M

RATE = 5            # Hz, the GPS steps of the hand-made flights
IMU_HZ = 100        # Hz, their IMU
RANK = {"events": 0, "height": 2, "impacts": 3}      # the order at equal times of step_alerts


def times(t0: float, t1: float, rate: int = RATE) -> np.ndarray:
    """Steps at ``rate`` from t0 to t1 (excluded), exact multiples of 1/rate."""
    return np.arange(round(t0 * rate), round(t1 * rate)) / rate


def flight(spikes: list[float], t_end: float = 60.0, seed: int = 3):
    """One flight's rows (chi-square NIS at RATE with 1 s spikes at ``spikes``), a chi2 gate fit
    and calibrated on them, and its scores."""
    t = times(0, t_end)
    nis = np.random.default_rng(seed).chisquare(6, len(t))
    for s in spikes:
        nis[(t >= s) & (t < s + 1.0)] += 200.0
    rows = pd.DataFrame({"flight_id": np.zeros(len(t), np.int32), "t": t, "res_gps_nis": nis})
    det = make("chi2").fit(rows)
    det.calibrate(60.0)
    return rows, det, det.decision_function(rows)


def imu_frame(t_end: float, spike_at: float | None = None, spike_g: float = 5.0, n: int = 3,
              seed: int = 5) -> pd.DataFrame:
    """A vehicle's IMU at IMU_HZ (FLU, m/s^2): hover (1 g up, 0.05 g noise), with every tenth
    sample from 10 to 12 s a vibration spike of 8 g, and, at ``spike_at``, an impact: ``n``
    samples (10 ms each) of ``spike_g`` straight up."""
    t = times(0, t_end, IMU_HZ)
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, 0.05 * G0, (len(t), 3))
    a[:, 2] += G0
    vib = (t >= 10.0) & (t < 12.0) & (np.arange(len(t)) % 10 == 0)
    a[vib, 2] = 8.0 * G0
    if spike_at is not None:
        k = int(round(spike_at * IMU_HZ))
        a[k:k + n] = [0.0, 0.0, spike_g * G0]
    return pd.DataFrame({"t": t, "ax": a[:, 0], "ay": a[:, 1], "az": a[:, 2], "gx": 0.0, "gy": 0.0, "gz": 0.0})


def online(rows, scores, det, events=None, height=None, imu=None, rule=PhaseRule()):
    """The online step driven by hand, as a live driver does: the vehicle's events, heights and
    the IMU (sample by sample through ``ImpactDetector``) fed in time order before each row,
    the rest before the finish. Returns (alerts, every alert event)."""
    alarms = scores > det.threshold_
    step = OnlineStep(ScoredStream(scores, alarms, None, onset_flags(rows, det)), flight_ids=[0],
                      phase=FlightPhase(rule))
    items = []
    if events is not None:
        items += [(r.t, RANK["events"], r.event) for r in events.itertuples()]
    if height is not None:
        items += [(r.t, RANK["height"], r.h) for r in height.itertuples()]
    if imu is not None:
        detector = ImpactDetector()
        for r in imu.itertuples():
            hit = detector.update(r.t, r.ax, r.ay, r.az)
            if hit is not None:
                items.append((hit.t, RANK["impacts"], hit))
    items.sort(key=lambda x: x[:2])
    log, k = [], 0

    def feed(until: float) -> None:
        nonlocal k
        while k < len(items) and items[k][0] <= until:
            ti, rank, what = items[k]
            if rank == RANK["events"]:
                log.extend(step.event(ti, what))
            elif rank == RANK["height"]:
                log.extend(step.height(ti, what))
            else:
                log.extend(step.impact(ti, what.crash, what.detail))
            k += 1

    for tk in rows.t:
        feed(tk)
        log.extend(step.update_columns(tk, {}).events)
    feed(math.inf)
    log.extend(step.finish())
    return step.alerts, log


def labels(alerts) -> list[tuple]:
    return [(a.start_s, a.phase, a.reason) for a in alerts]


# -- a landing event --------------------------------------------------------------------------------

def test_an_alert_3_s_before_the_landed_event_is_relabelled_online_and_offline_alike():
    rows, det, scores = flight(spikes=[20.0, 47.0])
    events = pd.DataFrame({"t": [0.5, 2.0, 50.0], "event": ["armed", "takeoff", "landed"], "detail": ""})
    alerts, log = online(rows, scores, det, events=events)
    assert labels(alerts) == [(20.0, "air", None),                      # 30 s before: the headline
                              (47.0, "transition", "landing at t=50.0 s (landed event)")]
    # raised in the air, relabelled by the landed event, at its time
    assert [(e.event, e.alert.end_s, e.alert.phase) for e in log if e.alert.start_s == 47.0] == [
        ("alert_start", None, "air"), ("alert_end", 48.0, "air"), ("alert_relabel", 48.0, "transition")]
    relabel = log[-1]
    assert relabel.event == "alert_relabel" and relabel.t == 50.0 and relabel.was == "air"
    # offline: the same object over the batch-scored rows, the same alerts
    assert step_alerts(rows, scores, det, "shape", events=events) == alerts
    # the whole-log phases: the labels the alerts end with
    ph = phases(rows.t, events)
    assert [ph[rows.t.searchsorted(a.start_s)] for a in alerts] == ["air", "transition"]
    assert set(ph[(rows.t >= 40.0) & (rows.t < 50.0)]) == {"transition"} and ph[rows.t.searchsorted(39.8)] == "air"
    assert alert_counts(alerts) == {"alerts": 1, "alerts_ground": 0, "alerts_transition": 1, "alerts_degraded": 0,
                                    "alerts_total": 2}
    assert "in the landing transition" in str(alerts[1])
    # the landing explains the alarm: no attack shape is claimed for it (the one in the air keeps its)
    assert alerts[1].attack_type == "unexplained" and alerts[0].attack_type == "attack"
    assert str(alerts[1]).startswith("flight 0: unexplained alert at 47.0 s in the landing transition")
    # a longer land_s reaches the first alert too; 0 relabels nothing
    wide = PhaseRule(land_s=31.0)
    assert [a.phase for a in online(rows, scores, det, events=events, rule=wide)[0]] == ["transition"] * 2
    assert [a.phase for a in online(rows, scores, det, events=events, rule=PhaseRule(land_s=0.0))[0]] == ["air"] * 2


def test_a_disarm_in_the_air_is_a_landing_and_one_on_the_ground_is_not():
    fp = FlightPhase()
    fp.event(0.0, "armed")
    fp.event(1.0, "takeoff")
    fp.event(30.0, "disarmed")                    # in the air: the vehicle came down (or fell)
    (landing,) = fp.pop_landings()
    assert (landing.t, landing.seen_t, landing.how) == (30.0, 30.0, "disarmed event")
    fp.event(40.0, "armed")
    fp.event(45.0, "disarmed")                    # armed on the ground and disarmed again
    assert fp.pop_landings() == []


# -- the height alone ---------------------------------------------------------------------------------

def test_a_height_only_landing_is_dated_at_its_touchdown_and_relabels_at_its_hold():
    """No events: the height climbs 10 m from 5 s, comes down from 35 s and is within 0.5 m of the
    ground at 45 s, a landing known 3 s later (land_hold_s). Alerts at 37 s (8 s before the
    touchdown) and at 46 s (between the touchdown and its hold's end) end as transition."""
    rows, det, scores = flight(spikes=[20.0, 37.0, 46.0])
    t = times(0, 60, 10)
    h = np.interp(t, [0.0, 5.0, 10.0, 35.0, 45.0, 60.0], [50.0, 50.0, 60.0, 60.0, 50.0, 50.0])
    height = pd.DataFrame({"t": t, "h": h})
    alerts, log = online(rows, scores, det, height=height)
    why = "landing at t=44.5 s (height)"                # the first height within 0.5 m: 50.5 m at 44.5 s
    assert labels(alerts) == [(20.0, "air", None), (37.0, "transition", why), (46.0, "transition", why)]
    assert {e.t for e in log if e.event == "alert_relabel"} == {47.5}
    assert step_alerts(rows, scores, det, "shape", height=height) == alerts
    ph = phases(rows.t, height=height)
    assert [ph[rows.t.searchsorted(a.start_s)] for a in alerts] == ["air", "transition", "transition"]
    assert ph[rows.t.searchsorted(47.4)] == "transition" and ph[rows.t.searchsorted(47.6)] == "ground"


# -- an impact in the IMU -------------------------------------------------------------------------------

def test_a_5_g_spike_is_an_impact_and_vibration_is_not():
    imu = imu_frame(40.0, spike_at=30.0)
    got = impacts(imu)
    assert list(got.columns) == ["t", "event", "detail", "g", "crash"]
    (hit,) = got.itertuples()                     # the 8 g vibration samples at 10-12 s are not impacts
    assert hit.event == "impact" and 30.0 <= hit.t <= 30.05 and not hit.crash
    assert hit.g > 3.0 and hit.detail == f"impact: {hit.g:.1f} g"
    # a per-sample rule would take vibration for an impact: the 50 ms mean does not
    per_sample = impacts(imu, ImpactRule(window_s=0.0))
    assert len(per_sample) == 3 and per_sample.t.iloc[0] == 10.0
    # 50 ms of 7 g: an impact, then a crash (more than 4 g above 1 g); a sustained 0.1 g is a free fall
    assert impacts(imu_frame(40.0, spike_at=30.0, spike_g=7.0, n=5)).crash.tolist() == [False, True]
    fall = imu_frame(40.0)
    fall.loc[(fall.t >= 20.0) & (fall.t < 20.5), ["ax", "ay", "az"]] = 0.1 * G0 / math.sqrt(3)
    (drop,) = impacts(fall).itertuples()
    assert drop.t == pytest.approx(20.13, abs=0.011) and drop.detail.startswith("impact: free fall 0.1")
    assert drop.g < 0.3 and not drop.crash


def test_impacts_online_equal_the_whole_frame():
    imu = imu_frame(40.0, spike_at=30.0, spike_g=7.0, n=5)
    imu.loc[(imu.t >= 20.0) & (imu.t < 20.5), ["ax", "ay", "az"]] = 0.0     # a free fall
    imu.loc[[100, 2001], "ax"] = np.nan                                     # dropped samples: left out
    imu.loc[3200:3204, "az"] = 4.0 * G0                                     # another impact, 2 s later
    offline = impacts(imu)
    detector = ImpactDetector()
    hits = [m for r in imu.itertuples() if (m := detector.update(r.t, r.ax, r.ay, r.az)) is not None]
    assert [(m.t, m.crash, m.detail) for m in hits] == list(zip(offline.t, offline.crash, offline.detail))
    np.testing.assert_allclose([m.g for m in hits], offline.g, rtol=1e-9, atol=1e-9)
    assert [d.split(":")[0] for d in offline.detail] == ["impact", "impact", "crash", "impact"]
    assert offline.detail[0].startswith("impact: free fall")


def test_upside_down_is_a_crash_and_a_flip_flown_out_of_is_not():
    """A multirotor's rotors push along its up axis: a negative up component for 0.3 s is a
    vehicle upside down (a loss of control that no spike dates: 112 of the field set). One 0.2 s
    long (a flip) is no crash; free fall and hover are not either."""
    imu = imu_frame(40.0)
    imu.loc[(imu.t >= 30.0), "az"] = -G0                          # at rest upside down from 30 s
    imu.loc[(imu.t >= 20.0) & (imu.t < 20.2), "az"] = -0.9 * G0   # a 0.2 s flip, flown out of
    (hit,) = impacts(imu).itertuples()
    assert hit.crash and hit.t == pytest.approx(30.34, abs=0.011) and hit.detail.startswith("crash: upside down 0.3")
    detector = ImpactDetector()
    online_hits = [m for r in imu.itertuples() if (m := detector.update(r.t, r.ax, r.ay, r.az)) is not None]
    assert [(m.t, m.crash, m.detail) for m in online_hits] == [(hit.t, True, hit.detail)]
    assert impacts(imu, ImpactRule(inverted_s=0.15)).t.round(2).tolist() == [20.19, 30.19]
    # the alert raised as it flipped is the crash's (the data ends 1.7 s after), not spoofing in the air
    rows, det, scores = flight(spikes=[29.0], t_end=32.0)
    events = pd.DataFrame({"t": [0.5, 2.0], "event": ["armed", "takeoff"], "detail": ""})
    alerts, _ = online(rows, scores, det, events=events, imu=imu)
    assert labels(alerts) == [(29.0, "transition", f"landing at t={hit.t:.1f} s ({hit.detail})")]
    assert step_alerts(rows, scores, det, "shape", events=events, impacts=impacts(imu)) == alerts
    # flown on for 5 s and more after it: no landing, the alert stays in the air
    rows, det, scores = flight(spikes=[29.0], t_end=40.0)
    imu.loc[(imu.t >= 30.5), "az"] = G0                           # righted again (a test rig's flip)
    assert [a.phase for a in online(rows, scores, det, events=events, imu=imu)[0]] == ["air"]


def test_an_impact_relabels_an_alert_2_s_before_it_and_holds_a_transition_after():
    """Armed, taken off, no landed event (a hard landing or a crash says none): a 5 g spike at
    30 s near the ground (the height back at the ground's) relabels the alert of 28 s; the alert
    of 31 s is raised in the impact's hold (5 s), that of 37 s in the air again."""
    rows, det, scores = flight(spikes=[28.0, 31.0, 37.0], t_end=40.0)
    events = pd.DataFrame({"t": [0.5, 2.0], "event": ["armed", "takeoff"], "detail": ""})
    t = times(0, 40, 10)
    height = pd.DataFrame({"t": t, "h": np.interp(t, [0.0, 2.0, 7.0, 25.0, 29.0], [80.0, 80.0, 90.0, 90.0, 80.3])})
    imu = imu_frame(40.0, spike_at=30.0)
    hit = impacts(imu).t.iloc[0]
    why = f"landing at t={hit:.1f} s (impact: {impacts(imu).g.iloc[0]:.1f} g)"
    alerts, log = online(rows, scores, det, events=events, height=height, imu=imu)
    assert labels(alerts) == [(28.0, "transition", why), (31.0, "transition", why), (37.0, "air", None)]
    # relabelled by the impact, or raised in its hold: the landing explains them, no attack shape
    assert [a.attack_type for a in alerts] == ["unexplained", "unexplained", "attack"]
    (relabel,) = [e for e in log if e.event == "alert_relabel"]
    assert (relabel.t, relabel.alert.start_s, relabel.was) == (hit, 28.0, "air")
    assert step_alerts(rows, scores, det, "shape", events=events, height=height, impacts=impacts(imu)) == alerts
    ph = phases(rows.t, events, height, impacts=impacts(imu))
    assert [ph[rows.t.searchsorted(a.start_s)] for a in alerts] == [a.phase for a in alerts]
    assert alert_counts(alerts)["alerts"] == 1 and alert_counts(alerts)["alerts_transition"] == 2
    # high up, the same spike is no landing; a crash is one wherever it happens, once the vehicle is
    # seen down after it (here: disarmed 2 s later), and none when it flies on (a spoof that makes
    # the vehicle jerk does not get its alert relabelled)
    high = height.assign(h=height.h + np.where(height.t > 20.0, 30.0, 0.0))
    assert [a.phase for a in online(rows, scores, det, events=events, height=high, imu=imu)[0]] == ["air"] * 3
    assert [a.phase for a in online(rows, scores, det, events=events, imu=imu)[0]] == ["air"] * 3   # no height
    crash = imu_frame(40.0, spike_at=30.0, spike_g=7.0, n=5)
    assert [a.phase for a in online(rows, scores, det, events=events, imu=crash)[0]] == ["air"] * 3  # flies on
    down = pd.concat([events, pd.DataFrame({"t": [32.0], "event": ["disarmed"], "detail": ""})], ignore_index=True)
    assert [a.phase for a in online(rows, scores, det, events=down, imu=crash)[0]] == [
        "transition", "transition", "ground"]


# -- the live monitor's side ------------------------------------------------------------------------------

def test_the_monitor_writes_the_relabel_and_its_alert_list_shows_the_new_phase(tmp_path):
    """FlightState (the monitor's queue of the vehicle's inputs) fed the IMU sample by sample, the
    segment's step its rows, Alerting the events: the relabel is in alerts.jsonl and on the
    console, the kept alert and the counts take the landing transition."""
    rows, det, scores = flight(spikes=[27.0], t_end=40.0)
    imu = imu_frame(40.0, spike_at=30.0, spike_g=7.0, n=5)
    fs = FlightState()
    fs.message(2.0, M.mavlink2.MAVLink_extended_sys_state_message(0, M.mavlink2.MAV_LANDED_STATE_IN_AIR))
    step = OnlineStep(ScoredStream(scores, scores > det.threshold_), flight_ids=[0], phase=fs.phase,
                      health=ReceiverHealth(flight_id=0))
    lines, seen = [], []
    records = Records(tmp_path)
    alerting = Alerting(det, MonitorConfig(connect="udpin:127.0.0.1:0"), lines.append, seen.append)
    alerting.attach(None, records)
    row_t = iter(rows.t)
    nxt = next(row_t)
    down = False
    for r in imu.itertuples():
        if r.t >= 31.0 and not down:                   # the vehicle on the ground after its crash
            fs.message(31.0, M.mavlink2.MAVLink_extended_sys_state_message(0, M.mavlink2.MAV_LANDED_STATE_ON_GROUND))
            down = True
        fs.imu(r.t, np.array([r.ax, r.ay, r.az, 0.0, 0.0, 0.0]))
        while nxt is not None and nxt <= r.t:
            alerting.events(fs.feed(step, nxt), 0, math.nan, FUSING)
            out = step.update_columns(nxt, {})
            alerting.events(out.events, 0, float(out.score[0]), FUSING)
            nxt = next(row_t, None)
    alerting.events(fs.feed(step, math.inf) + step.finish(), 0, math.nan, FUSING)
    records.close()
    assert fs.counts["impacts"] == 2                    # 4.6 g, then 5.8 g: a crash
    on_disk = [json.loads(x) for x in (tmp_path / "alerts.jsonl").read_text().splitlines()]
    assert [e["event"] for e in on_disk] == ["alert_start", "alert_end", "alert_relabel"]
    start, _, relabel = on_disk
    assert start["phase"] == "air" and seen[-1]["event"] == "alert_relabel"
    assert (relabel["start_s"], relabel["phase"], relabel["was"], relabel["kind"]) == (27.0, "transition", "air",
                                                                                      "spoofing")
    # dated at the crash, relabelled when the vehicle was seen down
    assert relabel["reason"] == "landing at t=30.0 s (crash: 5.8 g)" and relabel["vehicle_t"] == pytest.approx(31.0)
    (kept,) = alerting.alerts
    assert (kept.start_s, kept.phase, kept.reason) == (27.0, "transition", relabel["reason"])
    assert relabel["attack_type"] == kept.attack_type == "unexplained"
    assert {k: v for k, v in alerting.counts.items() if v} == {"alerts_transition": 1, "alerts_total": 1}
    assert any("alert of t 27.0 s: in the landing transition, not in the air" in line for line in lines)
    assert statustext(kept, 50.0) == "GPS SPOOF ALERT unexplained s=50 in landing"   # the crash explains it


# -- bad input ---------------------------------------------------------------------------------------------

def test_bad_input_is_refused_with_the_value_named():
    imu = imu_frame(2.0)
    with pytest.raises(ValueError, match="az missing"):
        impacts(imu.drop(columns="az"))
    with pytest.raises(ValueError, match="1 sample.* without a finite time"):
        impacts(imu.assign(t=np.where(imu.t == 1.0, np.nan, imu.t)))
    with pytest.raises(ValueError, match="in order"):
        impacts(imu.iloc[::-1])
    assert impacts(imu.iloc[:0]).empty
    for bad in ({"land_s": -1.0}, {"impact_hold_s": math.nan}, {"near_m": math.inf}, {"land_s": True}):
        with pytest.raises(ValueError, match=f"PhaseRule.{next(iter(bad))}"):
            PhaseRule(**bad)
    with pytest.raises(ValueError, match="crash_g"):
        ImpactRule(crash_g=1.0)
    with pytest.raises(ValueError, match="freefall_g"):
        ImpactRule(freefall_g=1.5)
    with pytest.raises(ValueError, match="finite"):
        FlightPhase().impact(math.nan, crash=True)
    with pytest.raises(ValueError, match="not finite"):
        phases([0.0, math.nan])
    with pytest.raises(ValueError, match="impacts: no column crash"):
        phases([0.0], impacts=pd.DataFrame({"t": [0.0]}))
    rows, det, scores = flight(spikes=[5.0], t_end=10.0)
    with pytest.raises(ValueError, match="impacts: columns crash missing"):
        step_alerts(rows, scores, det, "shape", impacts=pd.DataFrame({"t": [1.0], "detail": ["x"]}))
    with pytest.raises(ValueError, match="impacts: 1 row.* without a finite time"):
        step_alerts(rows, scores, det, "shape", impacts=pd.DataFrame({"t": [np.nan], "crash": [True]}))


def test_a_landing_takes_back_the_attack_shape_of_the_alert_it_explains():
    """An alert typed by shape (raised ``ramp``, confirmed ``bias``) that a landing relabels is
    typed ``unexplained``, confirmed type included; the tracker's other alerts keep theirs."""
    from quadformer.detectors.alarms import AlertTracker

    tr = AlertTracker(1)
    for t, on in ((1.0, True), (1.2, False), (3.0, True), (3.2, False)):
        tr.update(t, np.array([50.0 if on else 0.0]), np.array([on]), attack_type=np.array(["ramp"], dtype=object))
    tr.confirm(0, 1.0, "bias")
    tr.confirm(0, 3.0, "bias")
    ev = tr.relabel(0, 3.0, "transition", "landing at t=4.0 s (impact: 6.1 g)", 4.0, attack_type="unexplained")
    assert (ev.alert.attack_type, ev.alert.confirmed_type, ev.alert.phase, ev.was) == (
        "unexplained", "unexplained", "transition", "air")
    first = [a for _, _, a in tr.closed() if a.start_s == 1.0][0]
    assert (first.attack_type, first.confirmed_type, first.phase) == ("ramp", "bias", "air")
