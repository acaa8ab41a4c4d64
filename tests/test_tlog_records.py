"""A telemetry log read at once (``logs.tlog_records``) gives the messages pymavlink's reader gives
one by one, stamped alike; a log it cannot frame whole is left to pymavlink."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from quadformer.logs import read_log
from quadformer.logs.tlog import TAKEN
from quadformer.logs.tlog_records import whole_messages
from quadformer.sensors import mavlink as M

RECV0 = 1_700_000_000.0      # UNIX s of the first record


def _records() -> list[tuple[float, bytes]]:
    """10 s of a vehicle at rest, MAVLink 1 and 2 mixed as ground stations log them: IMU, attitude
    and heartbeats in MAVLink 2 (one signed), GPS in MAVLink 1, messages nobody reads (VFR_HUD,
    SYS_STATUS) and one of an id the dialect does not know."""
    mav1, mav2 = mavlink1.MAVLink(None, 1, 1), mavlink2.MAVLink(None, 1, 1)
    signed = mavlink2.MAVLink(None, 1, 1)
    signed.signing.secret_key, signed.signing.sign_outgoing = bytes(32), True
    out = []
    for k in range(500):
        t = 20.0 + 0.02 * k
        out.append((t, M.encode_highres_imu(t, np.array([0.0, 0.0, 9.81, 0.0, 0.0, 0.01 * k]),
                                            np.array([0.0, 0.2, -0.4])).pack(mav2)))
        if k % 5 == 0:
            out.append((t, M.encode_attitude(t, np.array([0.0, 0.0, 0.0, 1.0])).pack(mav2)))
            out.append((t, mavlink1.MAVLink_vfr_hud_message(1.0, 1.0, 90, 40, 10.0, 0.1).pack(mav1)))
        if k % 10 == 0:
            out.append((t, mavlink1.MAVLink_gps_raw_int_message(int(t * 1e6), 3, 473_977_418 + k, 85_455_939,
                                                                488_000, 90, 120, 0, 0, 12).pack(mav1)))
            out.append((t, mavlink2.MAVLink_sys_status_message(0, 0, 0, 500, 12000, -1, 80, 0, 0, 0, 0, 0, 0)
                        .pack(mav2)))
        if k % 50 == 0:
            hb = mavlink2.MAVLink_heartbeat_message(2, 3, 128 if k >= 150 else 0, 0, 4, 3)
            out.append((t, hb.pack(signed if k == 100 else mav2)))
            out.append((t, mavlink2.MAVLink_statustext_message(6, f"note {k}".encode()).pack(mav2)))
    unknown = bytearray(mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(mav2))
    unknown[7:10] = (0xFFFFF0).to_bytes(3, "little")             # an id no dialect has (no checksum checked)
    out.insert(7, (20.05, bytes(unknown)))
    return out


def _file(tmp_path, records, name="flight.tlog"):
    path = tmp_path / name
    path.write_bytes(b"".join(int((RECV0 + t - 20.0) * 1e6).to_bytes(8, "big") + pkt for t, pkt in records))
    return path


def _pymavlink(path):
    """(records, the messages of the types read_tlog takes) as pymavlink's reader gives them."""
    conn = mavutil.mavlink_connection(str(path), robust_parsing=True, dialect="ardupilotmega")
    got = []
    while (m := conn.recv_msg()) is not None:
        got.append(m)
    conn.close()
    return len(got), [m for m in got if m.get_type() in TAKEN], got


def test_whole_records_give_pymavlinks_messages_and_stamps(tmp_path):
    path = _file(tmp_path, _records())
    count, expected, every = _pymavlink(path)
    assert not any(m.get_type() == "BAD_DATA" for m in every)
    conn = mavutil.mavlink_connection(str(path), robust_parsing=True, dialect="ardupilotmega")
    fast = whole_messages(path.read_bytes(), conn.mav, TAKEN)
    conn.close()
    assert fast is not None and fast[0] == count
    assert [m.get_type() for m in fast[1]] == [m.get_type() for m in expected]
    assert {"HIGHRES_IMU", "ATTITUDE", "GPS_RAW_INT", "HEARTBEAT", "STATUSTEXT"} <= {m.get_type() for m in fast[1]}
    for a, b in zip(fast[1], expected):
        assert a.to_dict() == b.to_dict() and a._timestamp == b._timestamp and a._link == b._link
        assert (a.get_srcSystem(), a.get_seq(), a.get_msgbuf()) == (b.get_srcSystem(), b.get_seq(), b.get_msgbuf())
    log = read_log(path)
    assert log.source == "mavlink-tlog" and len(log.gps) == 50 and len(log.imu) == 500
    assert not any("unreadable" in n for n in log.notes)


@pytest.mark.parametrize("damage", ["checksum", "garbage", "cut", "short-after-v2"])
def test_a_log_not_framed_whole_is_left_to_pymavlink(damage, tmp_path):
    records = _records()
    if damage == "checksum":
        t, pkt = records[40]
        records[40] = (t, pkt[:-1] + bytes([pkt[-1] ^ 0xFF]))
    elif damage == "garbage":
        t, pkt = records[40]
        records[40] = (t, pkt + b"\x00\x01\x02")
    elif damage == "short-after-v2":     # pymavlink reads 12 bytes after a MAVLink 2 packet: into the next record
        records.insert(41, (records[40][0], mavlink1.MAVLink_mission_current_message(3).pack(
            mavlink1.MAVLink(None, 1, 1))))
    data = _file(tmp_path, records).read_bytes()
    if damage == "cut":
        data = data[:-5]
    path = tmp_path / "damaged.tlog"
    path.write_bytes(data)
    conn = mavutil.mavlink_connection(str(path), robust_parsing=True, dialect="ardupilotmega")
    assert whole_messages(path.read_bytes(), conn.mav, TAKEN) is None
    conn.close()
    if damage != "cut":                   # pymavlink's reader reports bad data there, which the log's notes count
        assert any(m.get_type() == "BAD_DATA" for m in _pymavlink(path)[2])
    log = read_log(path)                  # read message by message, as before
    assert len(log.imu) >= 490 and log.source == "mavlink-tlog"
