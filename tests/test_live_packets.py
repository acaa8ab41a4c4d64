"""The live link's packets: each datagram parsed on its own, and loss, duplicates and reordering
counted per sender from the MAVLink sequence numbers (``live.packets``): hand-written sequences,
a pymavlink peer written apart from our sender, and our sender's seeded faults end to end, both
on 127.0.0.1 (bounded in packets; wall-clock limits are only a safety net)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from live_support import FILTER, LOCAL, Clock, Vehicle, gate, monitor

from quadformer.live.packets import Sequence, header, read_datagram
from quadformer.sender import SenderConfig, VehicleStreams, send
from quadformer.sensors import mavlink as M

V1, V2 = M.mavlink2.PROTOCOL_MARKER_V1, M.mavlink2.PROTOCOL_MARKER_V2


@pytest.fixture(scope="module")
def quiet():
    """A gate that never alarms."""
    return gate(1e9)


def feed(seq: Sequence, src, numbers, stamps=None) -> None:
    for i, n in enumerate(numbers):
        seq.packet(src, n % 256, None if stamps is None else stamps[i])


def counts(seq: Sequence) -> tuple[int, int, int]:
    return seq.counts["lost"], seq.counts["duplicate"], seq.counts["reordered"]


# -- 1. the rule on hand-written sequences ------------------------------------------------------------
def test_a_hand_written_schedule_counts_exactly_across_the_wrap_around():
    """From 250 on, through 255 -> 0: 253, 6 and 7 never come; 0 arrives after 1 and 4 after 5;
    1, 3, 4 and 8 arrive twice (a copy of a late packet, or of one that came in order, is a
    duplicate, never reordered and never lost)."""
    seq = Sequence()
    feed(seq, (1, 1), [250, 251, 252, 254, 255, 1, 0, 1, 2, 3, 5, 3, 4, 4, 8, 8, 9])
    assert counts(seq) == (3, 4, 2)


def test_a_each_case_of_the_window():
    seq = Sequence()
    feed(seq, (1, 1), [10, 11, 13])            # 12 skipped: lost
    assert counts(seq) == (1, 0, 0)
    feed(seq, (1, 1), [12])                    # it arrives late: reordered, not lost
    assert counts(seq) == (0, 0, 1)
    feed(seq, (1, 1), [12, 13])                # again, and the latest again: duplicates
    assert counts(seq) == (0, 2, 1)
    feed(seq, (1, 1), [9])                     # before the first packet followed: reordered, never lost
    assert counts(seq) == (0, 2, 2)
    feed(seq, (1, 1), [14 + 127])              # 127 skipped ...
    assert counts(seq) == (127, 2, 2)
    feed(seq, (1, 1), [14, 14 + 126])          # ... the oldest (127 behind) and the newest of them late
    assert counts(seq) == (125, 2, 4)


def test_a_senders_are_counted_apart_and_an_unchecked_packet_never_starts_one():
    seq = Sequence()
    feed(seq, (1, 1), [0, 1, 3])               # (1, 1) skips 2
    feed(seq, (1, 2), [0, 1, 2, 3])            # (1, 2)'s 2 is not (1, 1)'s
    assert counts(seq) == (1, 0, 0)
    seq.packet((7, 7), 5, None, checked=False)  # a message outside the dialect from no followed sender
    seq.packet((7, 7), 9, None, checked=False)
    assert (7, 7) not in seq.senders and counts(seq) == (1, 0, 0)
    seq.packet((1, 1), 2, None, checked=False)  # from a followed one it counts: the late 2
    assert counts(seq) == (0, 0, 1)


def test_a_an_outage_of_whole_wrap_arounds_is_reckoned_from_the_stamps():
    """100 packets a second for 3 s; 510 lost (d = 254, one wrap-around); a packet from inside
    the outage arrives late: taken back out of lost. Then 600 lost ended by two unstamped
    packets (TIMESYNC, HEARTBEAT): reckoned at the next stamped one."""
    seq = Sequence()
    n = np.arange(300)
    feed(seq, (1, 1), n, 100.0 + n / 100.0)
    last = 299
    seq.packet((1, 1), (last + 511) % 256, 100.0 + (last + 511) / 100.0)
    assert counts(seq) == (510, 0, 0)
    seq.packet((1, 1), (last + 509) % 256, 100.0 + (last + 509) / 100.0)
    assert counts(seq) == (509, 0, 1)
    last += 511
    seq.packet((1, 1), (last + 1) % 256, None)
    seq.packet((1, 1), (last + 602) % 256, None)                 # 600 skipped: read as 88 so far
    assert counts(seq) == (509 + 88, 0, 1)
    seq.packet((1, 1), (last + 603) % 256, 100.0 + (last + 603) / 100.0)
    assert counts(seq) == (509 + 600, 0, 1)


# -- 2. which packets count -----------------------------------------------------------------------------
def test_b_a_message_outside_the_dialect_is_read_from_its_bytes():
    mav = M.mavlink2.MAVLink(None, srcSystem=7, srcComponent=3)
    mav.seq = 42
    buf = bytearray(M.encode_attitude(1.0, np.array([0.0, 0.0, 0.0, 1.0])).pack(mav))
    buf[7:10] = (60000).to_bytes(3, "little")                    # an id the dialect does not know
    v1 = bytes([V1, 2, 43, 7, 3, 240, 0, 0, 0, 0])                # MAVLink 1, id 240: not in the dialect
    rx = M.mavlink2.MAVLink(None)
    rx.robust_parsing = True
    (m2,), (m1,) = read_datagram(rx, bytes(buf)), read_datagram(rx, v1)
    assert (m2.get_type(), m1.get_type()) == ("UNKNOWN_60000", "UNKNOWN_240")
    assert header(m2) == ((7, 3), 42, False) and header(m1) == ((7, 3), 43, False)
    known = read_datagram(rx, M.encode_attitude(1.0, np.array([0.0, 0.0, 0.0, 1.0])).pack(mav))[0]
    assert header(known) == ((7, 3), 42, True)        # pack() leaves the sequence where it is


def test_b_a_junk_datagram_starting_with_a_marker_loses_no_valid_datagram(quiet):
    with monitor(quiet) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        peer.conn.write(b"\xfd\xff")                       # a MAVLink 2 marker claiming 255 bytes
        for k in range(30):
            peer.send(peer.raw_imu(100.0 + k / 100.0))
        peer.sync()
    s = out["summary"]
    assert s["messages"]["RAW_IMU"] == 30
    assert s["messages"]["BAD_DATA"] == 1 and s["link"]["corrupt_packets"] == 1
    assert s["link"]["lost_packets"] == 0


def test_b_a_thirty_percent_junk_datagrams_lose_nothing(quiet):
    rng = np.random.default_rng(7)
    junk = 0
    with monitor(quiet) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        for k in range(200):
            if rng.random() < 0.3:                          # 0xFD or 0xFE, then random bytes
                peer.conn.write(bytes([int(rng.choice([0xFD, 0xFE]))]) + rng.bytes(int(rng.integers(1, 40))))
                junk += 1
            peer.send(peer.raw_imu(100.0 + k / 100.0))
        peer.sync()
    s = out["summary"]
    assert junk > 40
    assert s["messages"]["RAW_IMU"] == 200
    assert s["link"]["corrupt_packets"] >= junk
    assert s["link"]["lost_packets"] == s["link"]["duplicate_packets"] == s["link"]["reordered_packets"] == 0


# -- 3. loss counted on the sequence together with the sender's time ------------------------------------------
def test_c_an_outage_longer_than_the_sequence_counts_every_lost_packet(quiet):
    with monitor(quiet) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        for k in range(300):                                # 3 s at 100 Hz: the sender's rate
            peer.send(peer.raw_imu(100.0 + k / 100.0))
        peer.sync()
        peer.conn.mav.seq = (peer.conn.mav.seq + 510) % 256  # 510 packets lost: 5.1 s at 100 Hz ...
        for k in range(100):                                # ... after the sync packet
            peer.send(peer.raw_imu(103.0 + 5.11 + k / 100.0))
        peer.sync()
    link = out["summary"]["link"]
    assert link["lost_packets"] == 510
    assert link["duplicate_packets"] == 0 and link["reordered_packets"] == 0


def test_c_an_outage_ended_by_an_unstamped_packet_is_reckoned_at_the_next_stamped_one(quiet):
    """A HEARTBEAT (no stamp) first after the outage: the next IMU packet's stamp times it."""
    with monitor(quiet) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        for k in range(300):
            peer.send(peer.raw_imu(100.0 + k / 100.0))
        peer.sync()
        peer.conn.mav.seq = (peer.conn.mav.seq + 600) % 256  # 600 packets lost: 6 s at 100 Hz
        peer.send(M.mavlink2.MAVLink_heartbeat_message(M.mavlink2.MAV_TYPE_QUADROTOR, M.mavlink2.MAV_AUTOPILOT_PX4,
                                                       0, 0, M.mavlink2.MAV_STATE_ACTIVE, 3))
        for k in range(50):
            peer.send(peer.raw_imu(109.0 + k / 100.0))
        peer.sync()
    assert out["summary"]["link"]["lost_packets"] == 600


def test_c_time_the_monitor_spends_away_from_the_link_is_no_loss(quiet):
    """The monitor's clock moves 6 s between two packets (a monitor busy, a machine suspended)
    while the vehicle's sequence and stamps go on: nothing was lost, whatever packet comes next."""
    clock = Clock()
    with monitor(quiet, clock=clock) as (mon, lines, out):
        peer = Vehicle(mon.address[1])
        for k in range(300):
            peer.send(peer.raw_imu(100.0 + k / 100.0))
        peer.sync()
        clock.skipped += 6.0
        peer.send(M.mavlink2.MAVLink_heartbeat_message(M.mavlink2.MAV_TYPE_QUADROTOR, M.mavlink2.MAV_AUTOPILOT_PX4,
                                                       0, 0, M.mavlink2.MAV_STATE_ACTIVE, 3))
        for k in range(50):
            peer.send(peer.raw_imu(103.0 + k / 100.0))
        peer.sync()
    assert out["summary"]["link"]["lost_packets"] == 0


# -- 4. our sender's faults, counted alike at both ends ------------------------------------------------------
def still_streams(seconds: float) -> VehicleStreams:
    """A vehicle at rest: IMU at 100 Hz, GPS at 10 Hz."""
    imu_t, gps_t = np.arange(int(seconds * 100)) / 100.0, np.arange(int(seconds * 10)) / 10.0
    return VehicleStreams(imu_t=imu_t, imu=np.tile([0.0, 0.0, 9.80665, 0.0, 0.0, 0.0], (len(imu_t), 1)),
                          gps_t=gps_t, gps_enu=np.zeros((len(gps_t), 3)), gps_vel=np.zeros((len(gps_t), 3)))


def test_d_the_senders_drops_reorders_duplicates_corruption_and_junk_are_counted_exactly(quiet):
    """A seeded fault schedule over 2,200 data packets: the monitor counts what the sender's
    report says it did, to the packet, and junk (some of it framing messages outside the
    dialect) never counts as a packet lost, duplicated or reordered."""
    cfg = SenderConfig(loss=0.03, corrupt=0.02, reorder=0.03, duplicate=0.03, junk=0.2, seed=11,
                       peer_timeout_s=60.0, sync_timeout_s=60.0, timeout_s=120.0)
    with monitor(quiet, filter=FILTER) as (mon, lines, out):
        report = send(still_streams(20.0), f"udpout:{LOCAL}:{mon.address[1]}", cfg)
        line = mon.status_line()
    assert report.data == 2200 and report.stalls == 0 and not report.timed_out
    assert (report.dropped, report.corrupted, report.reordered, report.duplicated, report.junk) == (71, 33, 58, 58, 431)
    s = out["summary"]
    link, messages = s["link"], s["messages"]
    assert (link["lost_packets"], link["duplicate_packets"], link["reordered_packets"]) == \
        (report.lost, report.duplicated, report.reordered) == (71 + 33, 58, 58)
    unknown = sum(v for k, v in messages.items() if k.startswith("UNKNOWN_"))
    assert unknown > 0                                      # junk that frames a message of an unknown id
    assert s["n_messages"] - messages["BAD_DATA"] - unknown == report.sent - report.corrupted
    assert messages["BAD_DATA"] >= report.corrupted + report.junk - unknown
    assert re.search(r"packets lost 104 bad \d+ dup 58 reord 58\b", line), line
