"""The live monitor's link intake against a MAVLink sender written apart from ours: a pymavlink
peer on 127.0.0.1 that stamps a stationary vehicle's IMU and GPS with its own boot clock
(``live_support``; the link's packets and their loss: ``test_live_packets``).

Every exchange ends with a TIMESYNC request the monitor answers once it has processed every
packet before it, so the tests wait for events and count messages; wall-clock limits are
only a safety net. Silence is made by moving the monitor's injected clock, never by sleeping."""

from __future__ import annotations

import csv
import json
import math
import re
import time

import numpy as np
import pytest
from live_support import FILTER, LOCAL, UP, Clock, Vehicle, gate, monitor

from quadformer.live.monitor import Monitor
from quadformer.sensors import mavlink as M
from quadformer.sensors.mavlink_link import open_link


@pytest.fixture(scope="module")
def quiet():
    """A gate that never alarms."""
    return gate(1e9)


# -- 3. a silent link is stale -------------------------------------------------------------------------
def test_c_a_silent_link_is_stale_and_fusing_again_when_data_flows(quiet, tmp_path):
    clock = Clock()
    with monitor(quiet, clock=clock, filter=FILTER, out=tmp_path, stale_s=5.0) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        peer.stream(4.0, attitude=True)
        peer.sync()
        assert mon.fixes > 10 and mon.state_text() == "fusing"
        clock.skipped += 10.0                              # 10 s without a packet
        assert mon.state_text() == "stale"
        line = mon.status_line()
        assert "stale" in line and re.search(r"no IMU for 1\d s", line) and re.search(r"no GPS for 1\d s", line)
        stale_summary = mon.summary()
        assert stale_summary["state"] == "stale"
        n = mon.fixes
        peer.stream(1.0)                                    # the vehicle's stamps go on
        peer.sync()
        assert mon.fixes > n and mon.state_text() == "fusing"
    assert out["summary"]["state"] == "fusing"


# -- 4. a stream slower than the filter needs is named ---------------------------------------------------
def test_d_an_imu_under_50_hz_is_warned_with_its_rate(quiet):
    with monitor(quiet, filter=FILTER) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        peer.stream(5.0, imu_hz=25.0, gps_hz=10.0 / 4, attitude=True)
        peer.sync()
    s = out["summary"]
    warnings = [n for n in s["notes"] if n.startswith("warning")]
    assert any(re.search(r"imu at 25 Hz .*under the 50 Hz the filter needs", n) for n in warnings), s["notes"]
    assert any(re.search(r"gps at 2\.5 Hz .*under the 5 Hz the filter needs", n) for n in warnings), s["notes"]
    assert any(w in lines for w in warnings)                # on the console too
    assert s["rates_hz"]["imu"] == pytest.approx(25.0, rel=0.02)


def test_d_streams_at_their_rates_give_no_warning(quiet):
    with monitor(quiet, filter=FILTER) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        peer.stream(5.0, attitude=True)
        peer.sync()
    s = out["summary"]
    assert not [n for n in s["notes"] if n.startswith("warning")], s["notes"]
    assert s["rates_hz"]["imu"] == pytest.approx(100.0, rel=0.02)
    assert s["rates_hz"]["gps"] == pytest.approx(10.0, rel=0.02)


# -- 5. one time base with detect: seconds since the link's first sensor sample ----------------------------
def test_e_times_count_from_the_first_sensor_sample_with_the_boot_time_beside(tmp_path):
    fixes = []
    detector = gate(-1.0)                                   # every fix alarms: alert events
    with monitor(detector, filter=FILTER, out=tmp_path, on_fix=fixes.append) as (mon, lines, out):
        peer = Vehicle(mon.address[1], boot=250.0)
        peer.stream(3.0, attitude=True)
        peer.sync()
        line = mon.status_line()
    assert fixes and fixes[0].t < 1.0 and all(0.0 <= f.t < 3.0 for f in fixes)
    now = re.search(r"\bt (\d+\.\d) s \(boot (\d+\.\d) s\)", line)
    assert now and float(now[1]) <= 3.0 and float(now[2]) - float(now[1]) == pytest.approx(250.0), line
    rows = list(csv.DictReader((tmp_path / "fixes.csv").open()))
    assert len(rows) == len(fixes)
    for r, f in zip(rows, fixes):
        assert float(r["t"]) == pytest.approx(f.t, abs=1e-5)
        assert float(r["boot_t"]) == pytest.approx(f.t + 250.0, abs=1e-5)
    events = [json.loads(x) for x in (tmp_path / "alerts.jsonl").read_text().splitlines()]
    start = next(e for e in events if e["event"] == "alert_start")
    assert start["t"] == pytest.approx(fixes[0].t) and start["boot_t"] == pytest.approx(fixes[0].t + 250.0)
    s = out["summary"]
    assert s["time"]["first_sample_boot_s"] == 250.0


# -- 6. repeated packets on the console --------------------------------------------------------------------
def test_f_duplicate_packets_show_on_the_status_line_and_in_the_summary(quiet):
    with monitor(quiet) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        for k in range(20):
            buf = peer.raw_imu(100.0 + k / 100.0).pack(peer.conn.mav)
            peer.conn.mav.seq = (peer.conn.mav.seq + 1) % 256
            peer.conn.write(buf)
            if k % 5 == 0:
                peer.conn.write(buf)                        # the same packet again: 4 duplicates
        peer.sync()
        line = mon.status_line()
    s = out["summary"]
    assert s["link"]["duplicate_packets"] == 4
    assert re.search(r"packets lost 0 bad 0 dup 4\b", line), line
    assert "duplicate packets 4" in Monitor.summary_text(s)




# -- 7. the vehicle's state: its flight phase and its receiver's health ---------------------------------------
def test_g_a_fix_lost_in_the_air_is_a_degraded_alert_before_any_fix_returns(quiet):
    """The vehicle arms and takes off (HEARTBEAT, EXTENDED_SYS_STATE: untimed, at the link's
    latest t), flies, then its receiver reports no fix and no position for 1 s: the degraded
    alert comes with the reports, while no fix is scored, labelled in the air; the fix's return
    ends it hold_s (3 s) later. The GPS admission never reads the phase or the health."""
    fixes, alerts = [], []
    with monitor(quiet, filter=FILTER, on_fix=fixes.append, on_alert=alerts.append) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        peer.stream(2.0, attitude=True)
        peer.sync()
        mode = M.mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
        peer.send(M.mavlink2.MAVLink_heartbeat_message(M.mavlink2.MAV_TYPE_QUADROTOR, M.mavlink2.MAV_AUTOPILOT_PX4,
                                                       mode, 0, M.mavlink2.MAV_STATE_ACTIVE, 3))
        peer.send(M.mavlink2.MAVLink_extended_sys_state_message(0, M.mavlink2.MAV_LANDED_STATE_IN_AIR))
        peer.stream(6.0)                                      # the take-off transition (5 s), then air
        peer.sync()
        assert mon.flight.phase.update(7.5) == "air" and not alerts
        lost_at = peer.t - 100.0                              # t of the first report without a fix
        nowhere = M.INT32_MAX * 1e-7
        for k in range(100):                                  # 1 s: IMU at 100 Hz, no fix at 10 Hz
            t = peer.t + k / 100.0
            peer.send(M.encode_highres_imu(t, imu=UP))
            if k % 10 == 0:
                peer.send(M.encode_gps_raw_int(t, nowhere, nowhere, 0.0, np.full(3, np.nan), fix_type=0,
                                               satellites=3))
        peer.t += 1.0
        peer.sync()
        (start,) = alerts
        assert (start["event"], start["kind"], start["phase"], start["reason"]) == (
            "alert_start", "degraded", "air", "fix lost (fix type 0)")
        assert start["vehicle_t"] == pytest.approx(lost_at) and start["score"] is None
        assert max(f.t for f in fixes) < lost_at                # raised with no fix since the loss
        assert "receiver degraded: fix lost (fix type 0)" in mon.status_line()
        peer.stream(5.0)
        peer.sync()
    end = alerts[-1]
    assert end["event"] == "alert_end" and end["vehicle_t"] == pytest.approx(lost_at + 1.0 + 3.0, abs=0.011)
    s = out["summary"]
    assert (s["alerts"], s["alerts_degraded"], s["alerts_total"]) == (0, 1, 1)
    assert s["flight"]["phase"] == "air" and s["flight"]["height_source"] == "gps"
    assert s["flight"]["inputs"]["armed"] == s["flight"]["inputs"]["takeoff"] == 1
    assert s["link"]["dropped"].get("gps_no_3d_fix", 0) == 0   # no position: no fix sample, a report only
    assert {f.admission for f in fixes} == {"fusing"}
    assert [f.phase for f in fixes if f.t > 7.0] == ["air"] * sum(f.t > 7.0 for f in fixes)
    assert any(line.endswith("GPS DEGRADED: fix lost (fix type 0), in the air, segment 0, fusing") for line in lines)


# -- 8. the autopilot's own test ratios: decoded, recorded beside the scores, asked for -------------------------
def _wire(msg):
    """A message as a link carries it: packed and parsed by pymavlink (float32 fields)."""
    mav = M.mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    return mav.decode(bytearray(msg.pack(mav)))


def test_h_estimator_status_messages_decode_to_the_square_roots_of_the_test_ratios():
    """ArduPilot's EKF_STATUS_REPORT (its *_variance fields: the square roots of the test ratios
    XKF4 logs, untimed) and PX4's ESTIMATOR_STATUS (*_ratio, stamped) decode into
    ``EstimatorRatios``; a ratio computed by ArduPilot's definition (``logs.ardupilot_ratios``) comes
    back as the square of what the message carries. Neither is a sensor sample."""
    from quadformer.logs.ardupilot_ratios import innovation_test_ratios

    innov = np.array([[0.6, 0.8, 0.5, 0.3, 0.4, 0.2]])             # position x, y, z, velocity x, y, z
    var = np.array([[0.5, 0.7, 1.2, 0.1, 0.12, 0.2]])
    ratio = innovation_test_ratios(innov, var, (5.0, 5.0, 5.0))
    ekf = _wire(M.encode_ekf_status_report(*(float(np.sqrt(ratio[f"ratio_{g}"][0])) for g in ("vel", "pos", "hgt")),
                                           mag=0.25, terrain=0.0, airspeed=0.0, flags=0x1FF | M.EKF_GPS_GLITCHING))
    r = M.estimator_ratios(ekf)
    assert r.source == "EKF_STATUS_REPORT" and math.isnan(r.t) and r.gps_glitch and r.flags & 0x1FF == 0x1FF
    for g, v in (("vel", r.vel), ("pos", r.pos_horiz), ("hgt", r.pos_vert)):
        assert v ** 2 == pytest.approx(ratio[f"ratio_{g}"][0], rel=1e-6)
    assert r.mag == pytest.approx(0.25) and math.isnan(r.pos_horiz_accuracy) and M.decode(ekf) == []
    px4 = _wire(M.encode_estimator_status(12.345678, 0.4, 0.3, 0.2, mag=0.1, hagl=0.05, tas=0.0,
                                          flags=0x3FF | M.ESTIMATOR_GPS_GLITCH))
    r = M.estimator_ratios(px4)
    assert r.source == "ESTIMATOR_STATUS" and r.t == pytest.approx(12.345678) and r.gps_glitch
    assert (r.vel, r.pos_horiz, r.pos_vert, r.mag, r.terrain) == pytest.approx((0.4, 0.3, 0.2, 0.1, 0.05))
    assert (r.pos_horiz_accuracy, r.pos_vert_accuracy) == pytest.approx((0.5, 0.8)) and M.decode(px4) == []
    assert not M.estimator_ratios(_wire(M.encode_ekf_status_report(0.1, 0.1, 0.1))).gps_glitch
    assert M.estimator_ratios(_wire(M.encode_attitude(1.0, np.array([0.0, 0.0, 0.0, 1.0])))) is None


def test_h_the_autopilots_test_ratios_are_recorded_and_asked_for(quiet, tmp_path):
    """An ArduPilot vehicle's heartbeat: with ``request_rates`` the monitor asks for its
    EKF_STATUS_REPORT (SET_MESSAGE_INTERVAL, 10 Hz) beside the sensors. Its reports, untimed, are
    recorded at the link's latest t; an ESTIMATOR_STATUS at its own stamp on the link's time
    base; another system's are dropped. ``autopilot_ratios.csv`` holds one line each, the summary
    the counts, the last and the largest; nothing is scored from them."""
    with monitor(quiet, filter=FILTER, out=tmp_path, request_rates=True) as (mon, lines, out):
        peer = Vehicle(mon.address[1], boot=100.0)
        peer.send(M.mavlink2.MAVLink_heartbeat_message(M.mavlink2.MAV_TYPE_QUADROTOR,
                                                       M.mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                                       M.mavlink2.MAV_STATE_ACTIVE, 3))
        asked, end = {}, time.monotonic() + 30.0
        while M.mavlink2.MAVLINK_MSG_ID_EKF_STATUS_REPORT not in asked and time.monotonic() < end:
            m = peer.conn.recv_match(type="COMMAND_LONG", blocking=True, timeout=0.5)
            if m is not None and m.command == M.mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
                asked[int(m.param1)] = 1e6 / m.param2
        assert asked.get(M.mavlink2.MAVLINK_MSG_ID_EKF_STATUS_REPORT) == pytest.approx(10.0), asked
        assert M.mavlink2.MAVLINK_MSG_ID_RAW_IMU in asked
        peer.stream(2.0, attitude=True)                          # boot 100 s is t = 0
        for vel in (0.2, 0.9, 0.4):
            glitch = M.EKF_GPS_GLITCHING if vel > 0.5 else 0
            peer.send(M.encode_ekf_status_report(vel, 0.3, 0.1, 0.05, flags=0x1FF | glitch))
        peer.send(M.encode_estimator_status(101.0, 0.5, 0.6, 0.7))
        other = open_link(f"udpout:{LOCAL}:{mon.address[1]}", 2, 1)
        other.mav.send(M.encode_ekf_status_report(3.0, 3.0, 3.0))
        other.close()
        peer.sync()
        now = mon.intake.now_t
    rows = list(csv.DictReader((tmp_path / "autopilot_ratios.csv").open()))
    assert [r["source"] for r in rows] == ["EKF_STATUS_REPORT"] * 3 + ["ESTIMATOR_STATUS"]
    assert [float(r["vel"]) for r in rows] == pytest.approx([0.2, 0.9, 0.4, 0.5])
    assert [int(r["gps_glitch"]) for r in rows] == [0, 1, 0, 0]
    assert all(float(r["t"]) == pytest.approx(now) for r in rows[:3]) and 1.9 < now < 2.0
    assert float(rows[3]["t"]) == pytest.approx(1.0) and float(rows[3]["boot_t"]) == pytest.approx(101.0)
    assert rows[0]["pos_horiz_accuracy"] == "" and float(rows[3]["pos_vert_accuracy"]) == pytest.approx(0.8)
    s = out["summary"]
    ratios = s["flight"]["autopilot_ratios"]
    assert ratios["max"] == pytest.approx({"vel": 0.9, "pos_horiz": 0.6, "pos_vert": 0.7, "mag": 0.05})
    assert ratios["last"]["source"] == "ESTIMATOR_STATUS" and ratios["last"]["t"] == pytest.approx(1.0)
    inputs = s["flight"]["inputs"]
    assert (inputs["ratios_EKF_STATUS_REPORT"], inputs["ratios_ESTIMATOR_STATUS"],
            inputs["ratios_gps_glitch"]) == (3, 1, 1)
    assert s["link"]["dropped"]["ratios_other_system"] == 1
    assert s["alerts_total"] == 0 and any("EKF_STATUS_REPORT 10 Hz" in n for n in s["notes"])
