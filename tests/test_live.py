"""The live MAVLink monitor: decoding, equivalence with offline detection on the same encoded
data, robustness to a bad link, vehicle actions, and the CLI. Real pymavlink peers on
127.0.0.1 with ephemeral ports; every loop and wait is bounded; fixed seeds."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from logs_support import FIX, time_limit
from typer.testing import CliRunner

from quadformer.cli import app
from quadformer.config import AttackConfig, SimConfig
from quadformer.detectors import alert_counts
from quadformer.detectors.alarms import Alert
from quadformer.evaluation.protocol import tune
from quadformer.estimator.online import FilterConfig
from quadformer.detectors.attack_types import SHAPE_TYPES
from quadformer.estimator.schema import ATTACK_TYPES
from quadformer.geometry.frames import euler_to_quat, geodetic_to_enu, quat_ned_frd_to_enu_flu, quat_to_matrix
from quadformer.live.alerts import describe, statustext
from quadformer.sensors.mavlink_link import local_address, open_link
from quadformer.sensors import mavlink as M
from quadformer.live.monitor import Monitor, MonitorConfig
from quadformer.sender import SenderConfig, VehicleStreams, send
from quadformer.logs import read_log
from quadformer.logs.detect import detect_log
from quadformer.logs.flightlog import assemble, make_stream
from quadformer.simulation import simulate_batch

EVENTS = FIX / "sample_px4_events.ulg"
LOCAL = "127.0.0.1"
SIM = SimConfig(model="I", sensors="gps+imu+mag+baro", flights=1, duration=30.0, seed=4,
                attack=AttackConfig(kind="bias", onset=(8.0, 9.0), duration=(5.0, 6.0), magnitude=(5.0, 6.0)))


# -- helpers ---------------------------------------------------------------------------------
def roundtrip(msg):
    """A message as a receiver gets it: packed by one MAVLink instance, parsed by another."""
    tx = M.mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    rx = M.mavlink2.MAVLink(None)
    out = rx.parse_buffer(msg.pack(tx))
    assert out is not None and len(out) == 1
    return out[0]


#: wall-clock safety nets, ten times what a loaded 2-core machine needs: the sender's flow
#: control (TIMESYNC answers) and the streams' length bound every run, not the wall clock
SAFETY_S = 600.0
PEER_WAIT_S = 100.0


def run_monitor(detector, streams, sender=SenderConfig(), seconds=SAFETY_S, **config):
    """Stream ``streams`` from a sender to a monitor on 127.0.0.1 (ephemeral port); returns
    (the monitor's fixes, its summary, the sender's report, its console lines). The sender
    waits for the monitor's answers as long as a loaded machine may need (a wait that gave up
    would let it run ahead and lose packets), within ``seconds`` of wall time."""
    sender = dataclasses.replace(sender, peer_timeout_s=PEER_WAIT_S, sync_timeout_s=PEER_WAIT_S, timeout_s=seconds)
    fixes, lines = [], []
    mon = Monitor(detector, MonitorConfig(connect=f"udpin:{LOCAL}:0", **config), on_fix=fixes.append,
                  echo=lines.append)
    mon.open()
    out = {}
    thread = threading.Thread(target=lambda: out.update(summary=mon.run()), daemon=True)
    thread.start()
    try:
        with time_limit(seconds):
            report = send(streams, f"udpout:{LOCAL}:{mon.address[1]}", sender)
    finally:
        mon.stop()
        thread.join(10)
    assert not thread.is_alive()
    return fixes, out["summary"], report, lines


def reference_log(record, path="live-record"):
    """The sender's data as encoded, as a FlightLog (what the monitor received), for the
    offline pipeline: fixes without a 3D fix are not fixes but receiver reports, as every GPS
    message is; the vehicle's events as the sender recorded them; ENU about the origin the
    vehicle sent, else the first fix (the monitor's rules). ``assemble`` counts time from the
    first sensor sample, as the monitor does."""
    gps = record["gps"]
    gps = gps[gps.fix_type >= 3].reset_index(drop=True)
    origin = record["origin"] or tuple(gps[["lat", "lon", "alt"]].iloc[0])
    enu = geodetic_to_enu(gps.lat.to_numpy(), gps.lon.to_numpy(), gps.alt.to_numpy(), origin)
    cols = {"imu": ["ax", "ay", "az", "gx", "gy", "gz"], "mag": ["mx", "my", "mz"], "baro": ["alt"],
            "attitude": ["qx", "qy", "qz", "qw"], "odometry": ["x", "y", "z", "vx", "vy", "vz", "qx", "qy", "qz", "qw"]}
    streams = {name: make_stream(name, record[name].t.to_numpy(), {c: record[name][c].to_numpy() for c in c_})
               for name, c_ in cols.items() if record[name] is not None}
    streams["gps"] = make_stream("gps", gps.t.to_numpy(), {
        "x": enu[:, 0], "y": enu[:, 1], "z": enu[:, 2],
        **{c: gps[c].to_numpy() for c in ("vx", "vy", "vz", "lat", "lon", "alt", "eph", "epv", "speed_acc",
                                          "fix_type", "satellites")}})
    rec = record["receiver"]
    streams["receiver"] = make_stream("receiver", rec.t.to_numpy(), {c: rec[c].to_numpy() for c in rec.columns[1:]})
    notes: list[str] = []
    log = assemble("arrays", Path(path), streams, notes, origin=origin, origin_source="live",
                   events=record["events"])
    assert len(log.segments) == 1, notes
    return log


# -- fixtures ----------------------------------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One torch thread, as the CLI runs the monitor (small tensors; two threads on a shared
    2-core machine double the time), restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def flight():
    """Simulated flights without a camera, in one batch: flight 0 (a bias attack, its sensors
    streamed by the tests) and flights 1 to 4 (the detector's training and validation)."""
    cfg = dataclasses.replace(SIM, flights=5)
    return simulate_batch(cfg, np.arange(5), np.array([True, True, False, True, False]), record_sensors=True)


@pytest.fixture(scope="module")
def detector(flight):
    """BHT on the GPS NIS, tuned on flights 1, 2 (train) and 3, 4 (validation)."""
    n = len(flight["t"])

    def table(ids):
        return pd.DataFrame({"flight_id": np.repeat(ids, n), "t": np.tile(flight["t"], len(ids)),
                             "label": flight["label"][ids].reshape(-1).astype(np.int8),
                             "res_gps_nis": flight["res_gps_nis"][ids, :, 0].reshape(-1)})

    train = table([1, 2])
    return tune("bht", train, train.label.to_numpy(), table([3, 4])).detector


@pytest.fixture(scope="module")
def sim_streams(flight):
    return VehicleStreams.from_simulation(flight["sensors"])


FILTER = FilterConfig.matching(SIM.to_dict(), sensors="gps+imu+mag")


# -- decoding ----------------------------------------------------------------------------------
def test_highres_imu_frd_to_flu_with_fields_updated():
    m = roundtrip(M.encode_highres_imu(12.345678, imu=np.array([0.5, -0.25, 9.75, 0.01, -0.02, 0.03]),
                                       mag=np.array([0.2, -0.05, -0.4]), pressure_alt=123.5))
    samples = M.decode(m)
    assert [type(s).__name__ for s in samples] == ["Mag", "Baro", "Imu"]      # CALL_ORDER at equal stamps
    mag, baro, imu = samples
    assert imu.t == 12.345678 and imu.source == "HIGHRES_IMU#0"
    np.testing.assert_allclose(imu.x, [0.5, -0.25, 9.75, 0.01, -0.02, 0.03], rtol=1e-6)   # float32 on the wire
    assert m.yacc == pytest.approx(0.25) and m.zacc == pytest.approx(-9.75)          # FRD on the wire
    np.testing.assert_allclose(mag.field, [0.2, -0.05, -0.4], rtol=1e-6)
    assert baro.alt == 123.5
    # only the fields marked updated become samples
    m.fields_updated = M.HIGHRES_MAG
    assert [type(s).__name__ for s in M.decode(m)] == ["Mag"]


@pytest.mark.parametrize("name, t_field, source", [("SCALED_IMU", "time_boot_ms", "SCALED_IMU#0"),
                                                   ("SCALED_IMU2", "time_boot_ms", "SCALED_IMU#1"),
                                                   ("SCALED_IMU3", "time_boot_ms", "SCALED_IMU#2"),
                                                   ("RAW_IMU", "time_usec", "RAW_IMU#0")])
def test_scaled_and_raw_imu_units(name, t_field, source):
    """mG, mrad/s, mgauss in FRD (ArduPilot sends RAW_IMU in the same scaling)."""
    cls = getattr(M.mavlink2, f"MAVLink_{name.lower()}_message")
    vals = {"xacc": 10, "yacc": -20, "zacc": -1000, "xgyro": 5, "ygyro": -7, "zgyro": 9, "xmag": 200, "ymag": 50,
            "zmag": -400, "temperature": 2500}
    if name == "RAW_IMU":
        vals["id"] = 0
    vals[t_field] = 2_500_000 if t_field == "time_usec" else 2500
    mag, imu = M.decode(roundtrip(cls(**{k: vals[k] for k in cls.fieldnames})))
    assert imu.t == pytest.approx(2.5) and imu.source == source
    g = 9.80665e-3
    np.testing.assert_allclose(imu.x, [10 * g, 20 * g, 1000 * g, 5e-3, 7e-3, -9e-3])
    np.testing.assert_allclose(mag.field, [0.2, -0.05, 0.4])
    vals.update(xmag=0, ymag=0, zmag=0)                                      # no compass: zeros
    assert [type(s).__name__ for s in M.decode(roundtrip(cls(**{k: vals[k] for k in cls.fieldnames})))] == ["Imu"]


def test_gps_raw_int_units_velocity_accuracies_and_sentinels():
    m = roundtrip(M.encode_gps_raw_int(3.0, 47.1234567, 8.5432101, 488.123, np.array([3.0, 4.0, -1.0]),
                                       eph=0.8, epv=1.2, speed_acc=0.25))
    (g,) = M.decode(m)
    assert (m.lat, m.lon, m.alt, m.vel) == (471234567, 85432101, 488123, 500)
    assert g.t == 3.0 and g.instance == 0 and g.fix_type == 3
    assert (g.lat, g.lon, g.alt) == (471234567 * 1e-7, 85432101 * 1e-7, 488123 * 1e-3)
    np.testing.assert_allclose(g.vel[:2], [3.0, 4.0], atol=1e-3)             # course over ground from north
    assert math.isnan(g.vel[2])                                              # no vertical velocity in GPS_RAW_INT
    assert (g.eph, g.epv, g.speed_acc) == pytest.approx((0.8, 1.2, 0.25))
    m.h_acc = 0
    m.cog = M.UINT16_MAX
    (g,) = M.decode(m)
    assert math.isnan(g.eph) and np.isnan(g.vel).all()                       # not sent; course unknown while moving
    m.vel = M.UINT16_MAX
    assert np.isnan(M.decode(m)[0].vel).all()
    m.lat = M.INT32_MAX
    assert M.decode(m) == []
    m2 = roundtrip(M.encode_gps_raw_int(1.0, 1.0, 2.0, 3.0, np.array([np.nan, np.nan, np.nan]), fix_type=2,
                                        instance=1))
    (g2,) = M.decode(m2)
    assert m2.get_type() == "GPS2_RAW" and g2.instance == 1 and g2.fix_type == 2 and np.isnan(g2.vel).all()
    assert math.isnan(g2.eph) and math.isnan(g2.speed_acc)


def test_attitude_and_odometry_frames():
    roll, pitch, yaw = 0.1, -0.2, 1.3
    (a,) = M.decode(roundtrip(M.mavlink2.MAVLink_attitude_message(1500, roll, pitch, yaw, 0, 0, 0)))
    assert a.t == 1.5
    np.testing.assert_allclose(a.q, quat_ned_frd_to_enu_flu(euler_to_quat(roll, pitch, yaw)), atol=1e-7)
    # yaw 0 in NED (nose north) is 90 deg in ENU (x east): the FLU x axis points north
    (a0,) = M.decode(roundtrip(M.mavlink2.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0, 0, 0)))
    np.testing.assert_allclose(quat_to_matrix(a0.q) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    q = np.array([0.1, -0.2, 0.3, 0.9])
    q /= np.linalg.norm(q)
    (o,) = M.decode(roundtrip(M.encode_odometry(2.0, np.array([1.0, 2.0, 3.0]), np.array([0.5, -1.0, 0.2]), q)))
    np.testing.assert_allclose(o.pos, [1, 2, 3], rtol=1e-6)
    np.testing.assert_allclose(o.vel, [0.5, -1.0, 0.2], atol=1e-6)          # body FRD on the wire, world ENU out
    np.testing.assert_allclose(o.q, q, atol=1e-6)
    # ENU world with the velocity in the world frame; an unsupported world frame gives nothing
    msg = M.mavlink2.MAVLink_odometry_message(1_000_000, 4, 4, 1.0, 2.0, 3.0, [float(q[3]), *map(float, q[:3])],
                                              0.5, -1.0, 0.2, 0, 0, 0, [math.nan] * 21, [math.nan] * 21, 0, 3, 100)
    (o2,) = M.decode(roundtrip(msg))
    np.testing.assert_allclose(o2.vel, [0.5, -1.0, 0.2], rtol=1e-6)
    msg.frame_id = 20                                                       # LOCAL_FRD: not north-aligned
    assert M.decode(roundtrip(msg)) == []
    msg.frame_id, msg.q = 1, [math.nan, 0, 0, 0]
    assert M.decode(roundtrip(msg)) == []


def test_pressure_origin_estimate_and_time():
    (b,) = M.decode(roundtrip(M.encode_scaled_pressure(4.0, 500.0)))
    assert b.t == 4.0 and b.alt == pytest.approx(500.0, abs=1e-3)
    assert M.pressure_altitude(1013.25) == 0.0 and M.pressure_altitude(899.0) == pytest.approx(1000.0, abs=5.0)
    (o,) = M.decode(roundtrip(M.encode_origin(47.1, 8.5, 400.25)))
    assert (o.lat, o.lon, o.alt, o.source) == (471000000 * 1e-7, 85000000 * 1e-7, 400.25, "GPS_GLOBAL_ORIGIN")
    (e,) = M.decode(roundtrip(M.mavlink2.MAVLink_global_position_int_message(7000, 471000000, 85000000, 401000,
                                                                             1000, 100, -200, 50, 0)))
    assert e.t == 7.0 and e.kind == "global"
    np.testing.assert_allclose(e.vel, [-2.0, 1.0, -0.5])                    # NED cm/s -> ENU m/s
    (lp,) = M.decode(roundtrip(M.mavlink2.MAVLink_local_position_ned_message(8000, 1.0, 2.0, 3.0, 0.1, 0.2, 0.3)))
    np.testing.assert_allclose(lp.pos, [2.0, 1.0, -3.0], rtol=1e-6)
    (st,) = M.decode(roundtrip(M.mavlink2.MAVLink_system_time_message(1_700_000_000_000_000, 5000)))
    assert st.unix_s == 1.7e9 and st.boot_s == 5.0
    assert M.decode(roundtrip(M.mavlink2.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3))) == []


def test_statustext_says_kind_phase_and_exclusion_in_50_characters():
    """What does not fit is left out: the score first, then the exclusion, the phase last."""
    spoof = Alert(0, 8.8, 8.8, "bias", 29.3, None)
    assert statustext(spoof, 29.3, exclusion=True) == "GPS SPOOF ALERT bias s=29.3 GPS excluded"
    on_ground = dataclasses.replace(spoof, attack_type="intermittent", phase="ground")
    assert statustext(on_ground, 29.3) == "GPS SPOOF ALERT intermittent s=29.3 on ground"
    assert statustext(dataclasses.replace(spoof, phase="transition"), 1234.5, exclusion=True) == \
        "GPS SPOOF ALERT bias in takeoff GPS excluded"
    assert statustext(dataclasses.replace(on_ground, phase="transition"), 1234.5, exclusion=True) == \
        "GPS SPOOF ALERT intermittent in takeoff"
    lost = Alert(0, 20.0, 20.0, "none", math.nan, None, kind="degraded", reason="fix lost (fix type 1)")
    assert statustext(lost, math.nan) == "GPS DEGRADED: fix lost"
    failsafe = dataclasses.replace(lost, phase="transition", reason="autopilot GPS failsafe")
    assert statustext(failsafe, math.nan) == "GPS DEGRADED: autopilot GPS failsafe in takeoff"
    assert statustext(dataclasses.replace(failsafe, reason="autopilot reports GPS lost"), math.nan) == \
        "GPS DEGRADED: autopilot reports GPS lost"                 # 51 characters with the phase
    alarm = dataclasses.replace(lost, attack_type="bias", score=7.0, phase="ground",
                                reason="accuracy jump (eph 7.0 m, median 1.0 m)")
    assert statustext(alarm, 7.0) == statustext(alarm, 7.0, exclusion=True) == \
        "GPS DEGRADED: accuracy jump alarm bias on ground"
    assert statustext(dataclasses.replace(alarm, attack_type="intermittent"), 7.0) == \
        "GPS DEGRADED: accuracy jump on ground"
    assert describe(alarm) == "degraded receiver (accuracy jump (eph 7.0 m, median 1.0 m)) on the ground"


# -- equivalence with offline detection ----------------------------------------------------------
def _same_as_offline(detector, fixes, summary, record, config):
    res = detect_log(reference_log(record), detector, config=config)
    assert summary["segments"] == 1 and summary["errors"] == 0
    t = np.array([f.t for f in fixes])
    scores = np.array([f.score for f in fixes])
    assert len(fixes) == len(res.rows) > 100
    np.testing.assert_array_equal(t, res.rows.t.to_numpy())
    np.testing.assert_allclose(scores, res.scores, rtol=0, atol=1e-9)
    np.testing.assert_array_equal([f.alarm for f in fixes], res.alarms)
    assert alert_rows(summary["alert_list"]) == alert_rows(dataclasses.asdict(a) for a in res.alerts)
    return res


def alert_rows(alerts) -> list[tuple]:
    """Alerts (as dicts) as tuples of every field, NaN as None, by start, kind and type: the
    monitor lists them as they end, detect by their start."""
    rows = [tuple(None if isinstance(v, float) and math.isnan(v) else v for v in a.values()) for a in alerts]
    return sorted(rows, key=lambda r: (r[1], r[7], r[3]))


def test_a_simulated_spoofed_flight_scores_as_offline_detection(detector, sim_streams, flight, tmp_path):
    """The vehicle arms at 1 s and takes off at 5 s (HEARTBEAT, EXTENDED_SYS_STATE), the attack
    begins near 8.8 s, in the take-off transition (5 s), and the receiver reports no fix from 20
    to 21.5 s: the same alerts, with the same kinds and flight phases, live and offline."""
    sender = SenderConfig(record=True, armed=(1.0, 60.0), in_air=(5.0, 60.0), fix_lost=(20.0, 1.5))
    fixes, summary, report, lines = run_monitor(detector, sim_streams, sender, filter=FILTER, out=tmp_path)
    assert report.lost == report.stalls == 0 and summary["link"]["lost_packets"] == 0
    res = _same_as_offline(detector, fixes, summary, report.record, FILTER)
    assert [e for _, e, _ in report.record["events"] if e != "mode"] == ["armed", "takeoff"]
    scored = [a for a in res.alerts if a.attack_type != "none"]
    assert scored and all(a.confirmed_type in ATTACK_TYPES for a in scored)
    assert summary["vehicle"]["origin_source"] == "first fix" and summary["vehicle"]["gps_receiver"] == 0
    onset = float(flight["attacks"].onset[0])           # t: 0 at the first sample
    first = min(scored, key=lambda a: a.start_s)
    assert onset <= first.start_s <= onset + 5.0 and (first.kind, first.phase) == ("spoofing", "transition")
    lost = [a for a in res.alerts if a.attack_type == "none"]
    assert [(a.kind, a.phase, a.reason) for a in lost] == [("degraded", "air", "fix lost (fix type 1)")]
    assert lost[0].start_s == pytest.approx(20.0 - sim_streams.start, abs=0.01)
    assert {(a.kind, a.phase) for a in res.alerts} == {("spoofing", "transition"), ("spoofing", "air"),
                                                       ("degraded", "air")}
    # counted apart in the summary, as detect counts a log's: the headline, spoofing in the air
    counts = alert_counts(res.alerts)
    assert {k: summary[k] for k in counts} == counts and counts["alerts_transition"] == 1
    assert summary["flight"]["phase"] == "air" and summary["flight"]["phase_source"] == "events"
    # what the vehicle and the records were told
    texts = report.statustexts          # rate-limited on the wall clock: the first five at least
    # the type at the alarm (the attack's first step: a guess) and the bias confirmed 5 s later
    assert texts[0] == (M.mavlink2.MAV_SEVERITY_ALERT, f"GPS SPOOF ALERT {first.attack_type} in takeoff GPS excluded")
    assert first.confirmed_type == "bias"
    assert all(t.startswith("GPS DEGRADED: fix lost" if sev == M.mavlink2.MAV_SEVERITY_WARNING else "GPS ")
               and len(t) <= 50 for sev, t in texts), texts
    assert any("spoofing in the take-off transition" in line for line in lines)
    assert any("] GPS DEGRADED: fix lost (fix type 1), in the air, segment 0," in line for line in lines), lines
    starts = [json.loads(x) for x in (tmp_path / "alerts.jsonl").read_text().splitlines()]
    starts = [e for e in starts if e["event"] == "alert_start"]
    assert sorted((e["kind"], e["phase"]) for e in starts) == sorted((a.kind, a.phase) for a in res.alerts)
    assert next(e for e in starts if e["attack_type"] == "none")["score"] is None
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert {k: on_disk[k] for k in counts} == counts
    phases = pd.read_csv(tmp_path / "fixes.csv").set_index("t")["phase"]    # take-off at 4.99 s
    assert phases.loc[5.0:9.9].eq("transition").all() and phases.loc[10.0:].eq("air").all()


def test_a_a_landing_relabels_the_alerts_before_it_live_as_offline(detector, sim_streams, tmp_path):
    """The flight of test_a, landing at 25 s (EXTENDED_SYS_STATE back on the ground): the degraded
    alert of the fix lost at 20 s, raised in the air, is relabelled the landing's transition
    when the landing is seen, live (alerts.jsonl, the alert list, the counts) as offline."""
    sender = SenderConfig(record=True, armed=(1.0, 60.0), in_air=(5.0, 25.0), fix_lost=(20.0, 1.5))
    fixes, summary, report, lines = run_monitor(detector, sim_streams, sender, filter=FILTER, out=tmp_path)
    assert report.lost == report.stalls == 0
    res = _same_as_offline(detector, fixes, summary, report.record, FILTER)
    assert [e for _, e, _ in report.record["events"] if e != "mode"] == ["armed", "takeoff", "landed"]
    (lost,) = [a for a in res.alerts if a.attack_type == "none"]
    assert (lost.kind, lost.phase) == ("degraded", "transition")
    assert lost.reason.startswith("fix lost (fix type 1); landing at t=") and lost.reason.endswith("(landed event)")
    records = [json.loads(x) for x in (tmp_path / "alerts.jsonl").read_text().splitlines()]
    relabels = [e for e in records if e["event"] == "alert_relabel"]
    assert lost.start_s in {e["start_s"] for e in relabels}
    assert all(e["phase"] == "transition" and e["was"] == "air" for e in relabels)
    assert any("in the landing transition, not in the air" in line for line in lines)
    counts = alert_counts(res.alerts)
    assert {k: summary[k] for k in counts} == counts


def test_b_a_px4_logs_sensors_score_as_offline_detection(detector):
    log = read_log(EVENTS)
    config = FilterConfig(sensors="gps+imu+mag+baro")
    fixes, summary, report, _ = run_monitor(detector, VehicleStreams.from_log(log), SenderConfig(record=True),
                                            filter=config)
    assert report.record["origin"] is not None                              # GPS_GLOBAL_ORIGIN was sent ...
    assert summary["vehicle"]["origin_source"] == "GPS_GLOBAL_ORIGIN"       # ... and used
    assert summary["link"]["dropped"].get("gps_no_3d_fix", 0) > 0           # the log's 2D fixes are not fixes
    _same_as_offline(detector, fixes, summary, report.record, config)


# -- a bad link ------------------------------------------------------------------------------------
def test_c_loss_duplicates_reordering_corruption_outages_and_a_restart_are_reported(detector, sim_streams):
    faults = SenderConfig(loss=0.05, duplicate=0.03, reorder=0.03, corrupt=0.02, seed=3, pause=(4.0, 2.2),
                          outages=((12.0, 4.0, ("gps",)), (18.0, 1.0, ("imu",))), restart_at=22.0, restart_to=0.5)
    fixes, s, report, lines = run_monitor(detector, sim_streams, faults, filter=FILTER, status_s=0.05)
    link = s["link"]
    assert s["errors"] == 0                                  # nothing was caught: every case is handled
    assert min(report.dropped, report.corrupted, report.duplicated, report.reordered) > 0
    assert (link["lost_packets"], link["duplicate_packets"], link["reordered_packets"], link["corrupt_packets"]) == \
        (report.lost, report.duplicated, report.reordered, report.corrupted)     # counted alike at both ends
    assert link["duplicates"] > 0 and link["late"] > 0
    reasons = [seg["started"] for seg in s["segment_list"]]
    assert any(r.startswith("IMU gap of") for r in reasons), reasons
    assert any("clock went back" in r for r in reasons), reasons
    assert s["segments"] == 3
    assert link["stream_gaps"]["gps"]["count"] >= 1 and link["stream_gaps"]["imu"]["count"] >= 1
    assert any(re.search(r"no GPS for \d+ s", line) for line in lines)
    assert any(re.search(r"no IMU for \d+ s", line) for line in lines)   # the pause
    assert len({f.segment for f in fixes}) == 3 and len(fixes) > 150


@pytest.mark.parametrize("missing", ["gps", "imu"])
def test_c_a_missing_stream_is_reported_and_nothing_is_scored(detector, sim_streams, missing):
    cfg = SenderConfig(skip=(missing,))
    fixes, s, report, lines = run_monitor(detector, sim_streams, cfg, filter=FILTER, status_s=0.05)
    assert fixes == [] and s["fixes_scored"] == 0 and s["errors"] == 0
    word = missing.upper()
    assert any(re.search(rf"no {word} for \d+ s", line) for line in lines)
    assert any(("waiting for fix" if missing == "gps" else "waiting for IMU") in line for line in lines)
    if missing == "imu":
        assert s["link"]["dropped"]["gps_without_imu"] > 0


# -- actions ---------------------------------------------------------------------------------------
def test_d_act_switches_the_ekf_source_set_and_back_and_alerts_arrive(detector, sim_streams):
    fixes, s, report, lines = run_monitor(detector, sim_streams, SenderConfig(), filter=FILTER, act=True,
                                          act_source_set=2, request_rates=True)
    switches = [p[0] for c, p in report.commands if c == M.mavlink2.MAV_CMD_SET_EKF_SOURCE_SET]
    assert switches[:2] == [2.0, 1.0], switches              # excluded, then re-admitted
    states = [f.admission for f in fixes]
    assert "GPS excluded" in states and states.index("GPS excluded") < states.index("re-admitting GPS")
    rates = {int(p[0]) for c, p in report.commands if c == M.mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert {M.mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU, M.mavlink2.MAVLINK_MSG_ID_GPS_RAW_INT} <= rates
    assert s["actions"]["commands_accepted"] == len(report.commands)       # the vehicle acknowledged each
    alerts = [text for sev, text in report.statustexts if sev == M.mavlink2.MAV_SEVERITY_ALERT]
    assert alerts and all(len(t) <= 50 for _, t in report.statustexts)
    assert "GPS SPOOF ALERT" in alerts[0] and "GPS excluded" in alerts[0]
    assert any("act: EKF source set 2" in line for line in lines)
    # the re-admission line says which rule re-admitted
    assert any(re.search(r"GPS re-admitted \((clear and agreeing for 2 s|agreeing for 5 s despite a standing alarm)\)",
                         line) for line in lines), lines


def test_d_console_names_the_readmission_rule(detector):
    """The monitor's admission under a standing alarm (the detector's memory) and fixes that
    agree: the stale rule re-admits and the console says so; a fix outside the gate under the
    same alarm excludes GPS again, with its reason."""
    lines = []
    mon = Monitor(detector, MonitorConfig(connect=f"udpin:{LOCAL}:0", filter=FILTER), echo=lines.append)
    seg = mon._new_segment("start")
    nis = np.full(80, 3.0)
    nis[:5] = 80.0
    nis[70] = 80.0
    for k in range(80):
        before = seg.state
        dec = seg.step.admission.decide(np.array([nis[k]]), np.zeros((1, 6)), np.array([True]), np.array([False]))
        mon._admission(k / 10.0, before, seg.state, int(dec.readmit[0]), int(dec.exclude[0]))
    text = "\n".join(lines)
    assert "[t 0.0 s] GPS excluded (detector alarm)" in text
    # agreeing from 0.5 s: the 50th agreeing fix, at 5.4 s, re-admits
    assert "[t 5.4 s] GPS re-admitted (agreeing for 5 s despite a standing alarm)" in text
    assert "[t 7.0 s] GPS excluded (fix outside the agreement gate under the standing alarm)" in text
    assert text.count("] GPS excluded (") == 2 and text.count("] GPS re-admitted (") == 1


# -- the CLI ---------------------------------------------------------------------------------------
def test_e_cli_monitor_end_to_end(detector, sim_streams, tmp_path):
    model = detector.save(tmp_path / "bht.json")
    conn = open_link(f"udpin:{LOCAL}:0", 1, 1)            # the vehicle side listens; the monitor connects out
    port = local_address(conn)[1]
    out = {}
    config = SenderConfig(speed=20.0, peer_timeout_s=PEER_WAIT_S, sync_timeout_s=PEER_WAIT_S, timeout_s=SAFETY_S)
    done = threading.Event()            # the monitor stopped: the sender stops too
    sender = threading.Thread(target=lambda: out.update(r=send(sim_streams, conn, config, stop=done)), daemon=True)
    sender.start()
    # the sender waits for the monitor (TIMESYNC), so a count of messages, not wall time, says
    # how far into the flight the monitor gets: 2500 of them are about 15 s of vehicle time, the
    # attack begins at 8-9 s; the duration only bounds a monitor that stalls
    with time_limit(SAFETY_S + 60):
        res = CliRunner().invoke(app, ["monitor", "--connect", f"udpout:{LOCAL}:{port}", "--model", str(model),
                                       "--sensors", "gps+imu+mag", "--max-messages", "2500",
                                       "--duration", f"{SAFETY_S:g}",
                                       "--out", str(tmp_path / "o")])
    done.set()
    sender.join(10)
    assert res.exit_code == 0, res.output
    assert "fixes scored" in res.output and "ALERT" in res.output
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["stop_reason"] == "max-messages" and summary["n_messages"] == 2500
    assert summary["fixes_scored"] > 100
    assert summary["config"]["connect"] == f"udpout:{LOCAL}:{port}" and summary["sensors"] == "gps+imu+mag"
    events = [json.loads(x) for x in (tmp_path / "o" / "alerts.jsonl").read_text().splitlines()]
    assert events and events[0]["event"] == "alert_start"
    assert {"vehicle_t", "wall_time", "score", "attack_type", "admission"} <= set(events[0])
    assert (tmp_path / "o" / "fixes.csv").read_text().count("\n") == summary["fixes_scored"] + 1


def test_e_cli_monitor_demo(tmp_path):
    with time_limit(SAFETY_S + 60):      # the demo's own flight and sender bound it
        res = CliRunner().invoke(app, ["monitor", "--demo", "--out", str(tmp_path / "demo"),
                                       "--duration", f"{SAFETY_S:g}"])
    assert res.exit_code == 0, res.output
    # alerts typed by shape: a kind when raised, confirmed 5 s later (vehicle time) for every alert
    assert re.search(rf"ALERT: ({'|'.join(SHAPE_TYPES)}), score", res.output), res.output
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    events = [json.loads(x) for x in (tmp_path / "demo" / "alerts.jsonl").read_text().splitlines()]
    starts = [e for e in events if e["event"] == "alert_start"]
    typed = [e for e in events if e["event"] == "alert_type"]
    assert [e["start_s"] for e in typed] == [e["vehicle_t"] for e in starts]
    assert [e["raised_as"] for e in typed] == [e["attack_type"] for e in starts]
    assert all(e["attack_type"] in ATTACK_TYPES for e in typed)
    # (those still pending when the stream ends are confirmed from its last fix)
    assert all(e["vehicle_t"] >= e["start_s"] + 5.0 - 1e-9 or e["vehicle_t"] == typed[-1]["vehicle_t"]
               for e in typed)
    assert "type" in res.output and "alert of t" in res.output
    assert summary["alerts"] >= 1 and (tmp_path / "demo" / "demo-model.json").exists()


def test_cli_monitor_without_a_model_takes_the_shipped_detector_of_its_sensors(tmp_path):
    from quadformer.detectors import pretrained

    with time_limit(60):        # nobody sends: the duration ends it
        r = CliRunner().invoke(app, ["monitor", "--connect", f"udpin:{LOCAL}:0", "--duration", "0.5",
                                     "--out", str(tmp_path / "a")])
    assert r.exit_code == 0, r.output
    default = pretrained.sets()["magbaro"].default
    assert f"detector: shipped {default}" in r.output and "chosen for a link" in r.output
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["detector"]["model"] == f"shipped:{default}" and summary["sensors"] == "gps+imu+mag+baro"
    with time_limit(60):
        r = CliRunner().invoke(app, ["monitor", "--connect", f"udpin:{LOCAL}:0", "--duration", "0.5",
                                     "--sensors", "gps+imu+vio", "--out", str(tmp_path / "b")])
    assert r.exit_code == 0, r.output
    assert f"detector: shipped {pretrained.sets()['vio'].default}" in r.output
    with time_limit(60):      # a vehicle without a compass: the magbaro default reads the GPS residues only
        r = CliRunner().invoke(app, ["monitor", "--connect", f"udpin:{LOCAL}:0", "--duration", "0.5",
                                     "--sensors", "gps+imu+baro", "--out", str(tmp_path / "c")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "c" / "summary.json").read_text())["sensors"] == "gps+imu+baro"


def test_cli_monitor_refuses_bad_input(tmp_path):
    r = CliRunner().invoke(app, ["monitor"])
    assert r.exit_code == 2 and "--connect is required" in r.output
    r = CliRunner().invoke(app, ["monitor", "--connect", f"udpin:{LOCAL}:0", "--sensors", "gps+vio"])
    assert r.exit_code == 2 and "no shipped detector fits ekf residues of gps+vio" in r.output
    r = CliRunner().invoke(app, ["monitor", "--stale-hold", "-1", "--connect", f"udpin:{LOCAL}:0"])
    assert r.exit_code == 2 and "stale_hold_s" in r.output
    r = CliRunner().invoke(app, ["monitor", "--model", str(tmp_path / "none.json"), "--connect", f"udpin:{LOCAL}:0"])
    assert r.exit_code == 2 and "no such model file" in r.output
    with pytest.raises(ValueError, match="monitor.typing: unknown 'labels'"):
        MonitorConfig(connect=f"udpin:{LOCAL}:0", typing="labels")


def test_fixes_read_with_jitter_are_fused_at_the_receivers_epochs(detector, sim_streams):
    """The autopilot's stamps jitter by 0 to 30 ms after each 10 Hz epoch (a link carries no time of
    week): the monitor finds the epochs from the stamps (``sensors.receiver_epochs``) and scores the
    fixes on the receiver's grid again, holding its IMU back for the late reads."""
    rng = np.random.default_rng(5)
    t = sim_streams.gps_t + rng.uniform(0.0, 0.03, len(sim_streams.gps_t))
    fixes, summary, report, _ = run_monitor(detector, dataclasses.replace(sim_streams, gps_t=t), filter=FILTER)
    assert report.lost == 0
    ep = summary["gps_epochs"]
    assert ep["restamped"] >= len(t) - 80 and ep["restarts"] == 0
    assert ep["jitter_ms"] == pytest.approx(30 / np.sqrt(12), rel=0.4)      # uniform 0..30 ms
    assert 20.0 < ep["hold_ms"] <= ep["largest_hold_ms"] < 35.0 and "epochs" in ep["note"]
    ft = np.array([f.t for f in fixes])
    steps = np.diff(ft[ft > ft[0] + 10.0])                                  # after the window's first 50 fixes
    assert len(steps) > 100 and np.abs(steps - 0.1).max() < 5e-3, np.abs(steps - 0.1).max()
    assert np.abs(np.diff(t) - 0.1).max() > 0.02                            # where the stamps' steps jitter
