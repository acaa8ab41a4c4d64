"""What the autopilot said happened (``FlightLog.events``) and the receiver's own status reports
(the ``receiver`` stream), from every reader that has them.

DataFlash and tlog files are written here from scratch (``logs_support.write_dataflash``,
pymavlink's message classes); PX4 uses pyulog's sample logs in tests/fixtures/logs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from pyulog import ULog

from quadformer.logs import FlightLog, LogError, read_log
from quadformer.logs.flightlog import EVENTS, make_events

from logs_support import FIX, write_dataflash

LAT0, LON0 = 42.85, -2.68


def _rows(log) -> list[tuple[float, str, str]]:
    return [(round(t, 6), e, d) for t, e, d in log.events.itertuples(index=False)]


# ============================================================================ DataFlash, TimeUS
def _copter_4(path: Path) -> Path:
    """ArduCopter 4.x layout: IMU at 50 Hz from 10 s after boot to 40 s, GPS at 5 Hz from 9 s
    (no fix before 10 s, and fix 1 from 20 s to 25 s), ARM, EV, ERR and MODE at stated times."""
    us = lambda s: int(round(s * 1e6))                       # noqa: E731
    timed = {                                                # boot s -> messages at that time
        12.0: [("ARM", [1]), ("EV", [10])],                   # one arming said twice
        13.0: [("EV", [15])],                                 # AUTO_ARMED while armed: no second arming
        14.0: [("EV", [28])],                                 # NOT_LANDED: takeoff
        15.0: [("MODE", [5, 5])], 16.0: [("MODE", [5, 5])],  # LOITER, then LOITER again: one change
        20.0: [("ERR", [11, 2])], 21.0: [("ERR", [7, 1])], 22.0: [("EV", [19])],   # LOST_GPS
        25.2: [("ERR", [11, 0])], 25.4: [("ERR", [7, 0])],
        30.0: [("MODE", [6, 6])], 31.0: [("ERR", [16, 2])], 32.0: [("ERR", [16, 0])],
        34.5: [("EV", [17])],                                 # LAND_COMPLETE_MAYBE: left out
        35.0: [("EV", [18])], 36.0: [("EV", [42])],           # LAND_COMPLETE; FENCE_DISABLE: left out
        38.0: [("EV", [11]), ("ARM", [0])],
    }
    msgs = [("MSG", [us(9.0), b"ArduCopter V4.3.0 (ef29350a)"])]
    for k in range(int(31 * 50)):                            # 9 s to 40 s in 20 ms steps
        s = 9.0 + 0.02 * k
        if s >= 10.0 - 1e-9:
            msgs.append(("IMU", [us(s), 0, 0.01, 0.0, 0.0, 0.0, 0.0, -9.81]))
        if k % 10 == 0:
            fix = 0 if s < 10.0 - 1e-9 else 1 if 20.0 - 1e-9 <= s < 25.0 - 1e-9 else 3
            lat, lon = (LAT0, LON0 + 1e-6 * k) if fix >= 2 else (0.0, 0.0)
            msgs.append(("GPS", [us(s), 0, fix, 4 if fix < 2 else 12, int(lat * 1e7), int(lon * 1e7), 500.0,
                                 0.5, 90.0, 0.0]))
        for name, values in timed.get(round(s, 2), []):
            msgs.append((name, [us(s), *values]))
    return write_dataflash(path, {
        "MSG": ("QZ", "TimeUS,Message"),
        "IMU": ("QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
        "GPS": ("QBBBLLffff", "TimeUS,I,Status,NSats,Lat,Lng,Alt,Spd,GCrs,VZ"),
        "ARM": ("QB", "TimeUS,ArmState"), "EV": ("QB", "TimeUS,Id"), "ERR": ("QBB", "TimeUS,Subsys,ECode"),
        "MODE": ("QMB", "TimeUS,Mode,ModeNum")}, msgs)


def test_dataflash_events_with_their_kinds_and_times_and_a_fix_loss_in_the_receiver(tmp_path):
    log = read_log(_copter_4(tmp_path / "copter-4.BIN"))
    assert log.imu.t.iloc[0] == 0.0 and log.boot_t0 == pytest.approx(10.0)     # t = 0 at the first IMU
    assert _rows(log) == [
        (2.0, "armed", "ARM ArmState 1"), (4.0, "takeoff", "EV Id 28"), (5.0, "mode", "MODE 5 LOITER"),
        (10.0, "gps_glitch", "ERR Subsys 11 ECode 2"), (11.0, "gps_failsafe", "ERR Subsys 7 ECode 1"),
        (12.0, "gps_lost", "EV Id 19"),
        (15.2, "gps_glitch_cleared", "ERR Subsys 11 ECode 0"), (15.4, "gps_failsafe_cleared", "ERR Subsys 7 ECode 0"),
        (20.0, "mode", "MODE 6 RTL"), (21.0, "ekf_variance", "ERR Subsys 16 ECode 2"),
        (22.0, "ekf_variance_cleared", "ERR Subsys 16 ECode 0"), (25.0, "landed", "EV Id 18"),
        (28.0, "disarmed", "ARM ArmState 0")]
    assert log.events.t.dtype == np.float64 and any("events: 2 repeated event(s)" in n for n in log.notes)
    # the receiver: every report, the 1 s without a fix before the IMU (negative t) and the fix loss
    rec, gps = log.receiver, log.gps
    assert len(rec) == 155 and rec.t.iloc[0] == pytest.approx(-1.0)
    loss = (rec.t >= 10.0 - 1e-9) & (rec.t < 15.0 - 1e-9)
    assert (rec.fix_type[loss] == 1).all() and loss.sum() == 25 and (rec.satellites[loss] == 4).all()
    assert (rec.fix_type[(rec.t >= 0) & ~loss] == 3).all()
    # the gps stream keeps fixes only: a 5.2 s gap over the loss, which splits the segments
    assert len(gps) == 155 - 5 - 25 and gps.t.iloc[0] == pytest.approx(0.0)
    assert np.diff(gps.t).max() == pytest.approx(5.2) and not ((gps.t > 9.81) & (gps.t < 14.99)).any()
    assert len(log.segments) == 2
    # a segment keeps the events inside it
    part = log.segment(1)
    assert part.events.t.min() >= log.segments[1][0] and part.events.event.tolist()[0] == "gps_glitch_cleared"
    assert set(part.events.event) <= set(log.events.event) and len(part.events) == 7


# ============================================================================ DataFlash, 3.2 layout
def test_dataflash_before_3_3_untimed_events_take_the_time_before_them(tmp_path):
    """ArduCopter 3.2/3.3 logs: EV, ERR and MODE carry no time; an arming logged before the first
    timed message takes that message's time, the others the time of the message before them."""
    boot0 = 20_000                                             # ms since boot of the first IMU sample
    msgs = [("MSG", [b"ArduCopter V3.3-dev (78b42024)"]), ("EV", [10])]
    events = {50: [("EV", [28]), ("MODE", [2, 500])], 250: [("ERR", [11, 2])], 270: [("ERR", [7, 1])],
              300: [("ERR", [11, 0]), ("ERR", [7, 0])], 450: [("EV", [18])], 480: [("EV", [11])]}
    for k in range(500):                                       # 10 s of IMU at 50 Hz
        ms = boot0 + 20 * k
        msgs.append(("IMU", [ms, 0.0, 0.0, 0.01, 0.1, 0.0, -9.81]))
        msgs += events.get(k, [])                              # untimed: the IMU's time
        if k % 10 == 0:                                        # 5 Hz GPS; no fix from 5 s to 6 s
            fix = 1 if 250 <= k < 300 else 3
            msgs.append(("GPS", [fix, 379_000_000 + ms, 1813, 9, 1.2, int(LAT0 * 1e7) if fix == 3 else 0,
                                 int(LON0 * 1e7) + k if fix == 3 else 0, 0.0, 514.0, 0.5, 90.0, 0.0, ms + 3]))
    path = write_dataflash(tmp_path / "copter-3.3.BIN", {
        "MSG": ("Z", "Message"),
        "IMU": ("Iffffff", "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
        "GPS": ("BIHBfLLfffffI", "Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs,VZ,T"),
        "EV": ("B", "Id"), "ERR": ("BB", "Subsys,ECode"), "MODE": ("MI", "Mode,ThrCrs")}, msgs)
    log = read_log(path)
    assert log.boot_t0 == pytest.approx(20.0)
    assert _rows(log) == [
        (0.0, "armed", "EV Id 10"), (1.0, "takeoff", "EV Id 28"), (1.0, "mode", "MODE 2 ALT_HOLD"),
        (5.0, "gps_glitch", "ERR Subsys 11 ECode 2"), (5.4, "gps_failsafe", "ERR Subsys 7 ECode 1"),
        (6.0, "gps_glitch_cleared", "ERR Subsys 11 ECode 0"), (6.0, "gps_failsafe_cleared", "ERR Subsys 7 ECode 0"),
        (9.0, "landed", "EV Id 18"), (9.6, "disarmed", "EV Id 11")]
    rec = log.receiver
    assert len(rec) == 50 and (rec.fix_type[(rec.t > 4.9) & (rec.t < 5.9)] == 1).all()
    assert len(log.gps) == 45 and np.diff(log.gps.t).max() == pytest.approx(1.2)


# ============================================================================ PX4
@pytest.mark.parametrize("name", ["sample_px4_events.ulg", "sample_log_small.ulg"])
def test_px4_arming_takeoff_and_landing_in_order_at_the_topics_times(name):
    log = read_log(FIX / name)
    ev = log.events
    first = {e: float(ev.t[ev.event == e].iloc[0]) for e in ("armed", "takeoff", "landed", "disarmed")}
    assert first["armed"] <= first["takeoff"] < first["landed"] <= first["disarmed"]
    # each at the sample of its topic where the state changes, on the streams' clock
    u = ULog(str(FIX / name), ["vehicle_land_detected", "vehicle_status"])
    land = u.get_dataset("vehicle_land_detected").data
    k = int(np.flatnonzero(np.diff(land["landed"].astype(int)) == -1)[0]) + 1
    assert first["takeoff"] == pytest.approx(land["timestamp"][k] * 1e-6 - log.boot_t0, abs=1e-6)
    k = int(np.flatnonzero(np.diff(land["landed"].astype(int)) == 1)[0]) + 1
    assert first["landed"] == pytest.approx(land["timestamp"][k] * 1e-6 - log.boot_t0, abs=1e-6)
    status = u.get_dataset("vehicle_status").data
    armed = status["arming_state"] == 2
    k = int(np.flatnonzero(armed[:-1] & ~armed[1:])[0]) + 1
    assert first["disarmed"] == pytest.approx(status["timestamp"][k] * 1e-6 - log.boot_t0, abs=1e-6)
    # every receiver report: at least the fixes, and fix_type < 2 before the first fix
    assert len(log.receiver) >= len(log.gps)
    assert log.receiver.fix_type[log.receiver.t < log.gps.t.iloc[0]].lt(2).all()


def test_px4_events_and_receiver_of_the_other_samples():
    small = read_log(FIX / "sample_log_small.ulg")
    # armed when the log starts: said at its first vehicle_status sample
    assert small.events.iloc[0].tolist()[1:] == ["armed", "vehicle_status.arming_state 2 at the log's start"]
    assert len(small.receiver) == len(small.gps) == 32
    np.testing.assert_array_equal(small.receiver.noise.unique(), [98, 99])     # noise_per_ms
    events = read_log(FIX / "sample_px4_events.ulg")
    gps = ULog(str(FIX / "sample_px4_events.ulg"), ["vehicle_gps_position"]).get_dataset("vehicle_gps_position").data
    ids, counts = np.unique(gps["device_id"], return_counts=True)
    fix = gps["fix_type"][gps["device_id"] == ids[np.argmax(counts)]]        # the device the gps stream keeps
    np.testing.assert_array_equal(events.receiver.fix_type, fix)
    assert (fix < 2).sum() > 100 and len(events.gps) == (fix >= 2).sum()
    tagged = read_log(FIX / "sample_logging_tagged_and_default_params.ulg")
    assert tagged.events.event.tolist() == ["mode"]                 # never armed, always landed
    assert read_log(FIX / "sample.ulg").receiver is None            # no GPS topic


# ============================================================================ tlog
def test_tlog_heartbeat_landed_state_and_status_texts_become_events(tmp_path):
    """10 s of a vehicle at 100 Hz: armed from 2 s to 8 s (HEARTBEAT), in the air from 3 s to 7 s
    (EXTENDED_SYS_STATE), LOITER from 5 s, no fix from 4 s to 6 s with "GPS Glitch" and "GPS Glitch
    cleared" texts; a camera's heartbeat (no autopilot) and a pre-arm text say nothing."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from quadformer.sensors import mavlink as M

    mav = mavlink2.MAVLink(None, 1, 1)
    recv0 = 1_700_000_000.0
    records = []
    for k in range(1000):
        s = 0.01 * k                                                # s after the first record
        t = 20.0 + s                                                # the vehicle's time since boot
        records.append((s, M.encode_highres_imu(t, np.array([0.0, 0.0, 9.81, 0.0, 0.0, 0.0])).pack(mav)))
        if k % 20 == 0:
            fix = 1 if 400 <= k < 600 else 3
            records.append((s, M.encode_gps_raw_int(t, LAT0 if fix == 3 else 0.0, LON0 if fix == 3 else 0.0, 500.0,
                                                    np.zeros(3), eph=0.8, fix_type=fix,
                                                    satellites=4 if fix == 1 else 12).pack(mav)))
        if k % 100 == 0:
            base = 1 | (128 if 200 <= k < 800 else 0)               # CUSTOM_MODE_ENABLED | SAFETY_ARMED
            records.append((s, mavlink2.MAVLink_heartbeat_message(2, 3, base, 5 if k >= 500 else 0, 4, 3).pack(mav)))
            records.append((s, mavlink2.MAVLink_heartbeat_message(30, 8, 0, 0, 0, 3).pack(mav)))   # a camera
            records.append((s, mavlink2.MAVLink_extended_sys_state_message(0, 2 if 300 <= k < 700 else 1).pack(mav)))
        text = {100: b"PreArm: GPS glitching", 450: b"GPS Glitch", 650: b"GPS Glitch cleared"}.get(k)
        if text:
            records.append((s, mavlink2.MAVLink_statustext_message(2, text).pack(mav)))
    path = tmp_path / "flight.tlog"
    path.write_bytes(b"".join(int((recv0 + s) * 1e6).to_bytes(8, "big") + pkt for s, pkt in records))
    log = read_log(path)
    got = [(round(t, 3), e, d) for t, e, d in log.events.itertuples(index=False)]
    assert got == [
        (0.0, "mode", "HEARTBEAT mode STABILIZE"), (2.0, "armed", "HEARTBEAT base_mode 129"),
        (3.0, "takeoff", "EXTENDED_SYS_STATE landed_state 2"), (4.5, "gps_glitch", "STATUSTEXT 'GPS Glitch'"),
        (5.0, "mode", "HEARTBEAT mode LOITER"), (6.5, "gps_glitch_cleared", "STATUSTEXT 'GPS Glitch cleared'"),
        (7.0, "landed", "EXTENDED_SYS_STATE landed_state 1"), (8.0, "disarmed", "HEARTBEAT base_mode 1")]
    rec, gps = log.receiver, log.gps
    assert len(rec) == 50 and len(gps) == 40
    loss = (rec.t > 3.99) & (rec.t < 5.99)
    assert (rec.fix_type[loss] == 1).all() and loss.sum() == 10 and (rec.satellites[loss] == 4).all()
    np.testing.assert_allclose(rec.eph, 0.8)
    assert not ((gps.t > 3.99) & (gps.t < 5.99)).any()


# ============================================================================ ROS
def test_rosbag_receiver_keeps_the_fixes_without_a_position_and_has_no_events(tmp_path):
    """A ROS 2 bag: IMU at 20 Hz for 5 s, NavSatFix at 5 Hz with status -1 (NO_FIX) for 2 s to 3 s."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    V3 = T["geometry_msgs/msg/Vector3"]
    level = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    base = 1_700_000_000 * 10**9

    def header(ns: int, frame: str):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id=frame)
    with Writer(tmp_path / "bag", version=9) as w:
        imu = w.add_connection("/mavros/imu/data_raw", "sensor_msgs/msg/Imu", typestore=store)
        fix = w.add_connection("/mavros/global_position/raw/fix", "sensor_msgs/msg/NavSatFix", typestore=store)
        for k in range(100):
            ns = base + k * 50_000_000
            w.write(imu, ns, store.serialize_cdr(T["sensor_msgs/msg/Imu"](
                header=header(ns, "base_link"), orientation=level,
                orientation_covariance=np.zeros(9), angular_velocity=V3(x=0.0, y=0.0, z=0.0),
                angular_velocity_covariance=np.zeros(9), linear_acceleration=V3(x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9)), "sensor_msgs/msg/Imu"))
            if k % 4 == 0:
                status = -1 if 40 <= k < 60 else 0
                w.write(fix, ns, store.serialize_cdr(T["sensor_msgs/msg/NavSatFix"](
                    header=header(ns, "gps"), status=T["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
                    latitude=LAT0, longitude=LON0, altitude=30.0, position_covariance=np.diag([4.0, 1.0, 9.0]).ravel(),
                    position_covariance_type=2), "sensor_msgs/msg/NavSatFix"))
    log = read_log(tmp_path / "bag")
    assert log.events is None
    rec = log.receiver
    assert len(rec) == 25 and len(log.gps) == 20
    np.testing.assert_array_equal(rec.fix_type, np.where((rec.t > 1.99) & (rec.t < 2.99), 0.0, 3.0))
    np.testing.assert_allclose(rec[["eph", "epv"]].to_numpy(), [[2.0, 3.0]] * 25)
    assert not ((log.gps.t > 1.99) & (log.gps.t < 2.99)).any()


# ============================================================================ validation
def test_events_are_validated_and_repeats_kept_once():
    notes: list[str] = []
    frame = make_events([(3.0, "landed", "EV Id 18"), (1.0, "armed", "ARM ArmState 1"), (1.2, "armed", "EV Id 10"),
                         (2.0, "mode", "MODE 5"), (2.1, "mode", "MODE 6"), (float("nan"), "takeoff", "EV Id 28")],
                        notes)
    assert frame.event.tolist() == ["armed", "mode", "mode", "landed"] and frame.t.is_monotonic_increasing
    assert any("non-finite time" in n for n in notes) and any("1 repeated" in n for n in notes)
    assert make_events([]) is None
    with pytest.raises(KeyError, match="unknown event"):
        make_events([(0.0, "crashed", "")])
    good = pd.DataFrame({"t": [0.0, 1.0], "event": ["armed", "takeoff"], "detail": ["a", "b"]})
    assert FlightLog("arrays", Path("x"), events=good).events is good
    for bad, match in ((good.assign(event=["armed", "crashed"]), "unknown event"),
                       (good.assign(t=[1.0, 0.0]), "non-decreasing"),
                       (good.assign(t=[0.0, np.nan]), "non-decreasing"),
                       (good[["t", "event"]], "columns"),
                       (good.iloc[:0], "empty")):
        with pytest.raises(LogError, match=match):
            FlightLog("arrays", Path("x"), events=bad)
    assert set(EVENTS) >= {"armed", "disarmed", "takeoff", "landed", "gps_glitch", "gps_failsafe", "mode"}
