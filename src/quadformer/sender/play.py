"""Playing a vehicle's sensor streams as MAVLink over a pymavlink link (``send``).

``VehicleStreams`` holds what a vehicle would stream (SI units, ENU world, FLU body): a
recorded log's sensors (``VehicleStreams.from_log``, any object with a ``FlightLog``'s
DataFrames) or a simulated flight's (``from_simulation``, the ``sensors`` entry of
``simulate_batch(..., record_sensors=True)``), optionally with a spoof injected into its GPS
(``with_attack``: an ``AttackBatch`` of one flight; a capture also changes the receiver fields
GPS_RAW_INT carries: eph, epv, vel_acc, satellites_visible, fix_type). ``send(streams, connect, config)`` plays them as
HIGHRES_IMU (IMU, and the magnetometer in the same message when stamped alike),
GPS_RAW_INT, ATTITUDE, SCALED_PRESSURE, ODOMETRY (with VIO) and a HEARTBEAT per vehicle
second (armed within ``armed``; with ``in_air``, EXTENDED_SYS_STATE beside it), in stamp
order and, for equal stamps, in ``estimator.online.CALL_ORDER`` (the order of the log
replay), faster than real time:

- ``speed``: times real time (None: no pacing);
- flow control (``window`` > 0): a TIMESYNC request every ``window // 4`` packets and at most
  ``window`` packets ahead of the last one the receiver answered (a live monitor answers
  TIMESYNC as a companion computer does), so a UDP receiver is never overrun: "as fast as the
  receiver keeps up".

Faults, seeded (``np.random.default_rng(seed)``; junk from a stream of its own, so that
the other faults of a seed do not depend on it): each data packet is dropped (its sequence
number used: a gap the receiver sees), corrupted (one byte after the header flipped: a bad
CRC, sent once in its place), held back behind the next intact data packet (reordered) or
sent twice (duplicated), at most one of these, drawn in that order; junk datagrams (a marker
byte and 1 to 40 random bytes, no sequence number used) before data packets; a silent pause,
an outage of some streams over a span of vehicle time, streams never sent, and a restart with
the vehicle's clock going back; a span in which the receiver reports no fix (``fix_lost``).
TIMESYNC, HEARTBEAT and EXTENDED_SYS_STATE packets are not faulted. The report counts as a
monitor counts (``live.packets``): ``lost`` the sequence numbers that reach the receiver in no
valid packet (dropped or corrupted), ``duplicated`` and ``reordered`` the intact packets that
arrive twice or after a later one.

With ``record=True`` the report holds the data exactly as encoded: every data packet that
left intact, parsed back and decoded (``mavlink.decode``), as FlightLog-like frames
(1e-7 deg, mm, cm/s and float32 quantisation included), with every GPS status report and the
vehicle's events (timed as a monitor times them: at the latest sample sent before them), so that
an offline reference can be computed on the very data the receiver got. Messages the receiver sends back (STATUSTEXT,
COMMAND_LONG, answered with COMMAND_ACK as a vehicle does) are collected in the report.
"""

from __future__ import annotations

import math
import time

import numpy as np

from quadformer.sender.config import SenderConfig, SendReport
from quadformer.sender.link import Peer, Recorder, pack
from quadformer.sender.streams import VehicleStreams, events, state_messages
from quadformer.sensors.mavlink import encode_origin, mavlink2
from quadformer.sensors.mavlink_link import open_link

__all__ = ["send"]


def send(streams: VehicleStreams, connect, config: SenderConfig = SenderConfig(), stop=None) -> SendReport:
    """Play ``streams`` to a MAVLink receiver. ``connect``: ``udpout:127.0.0.1:PORT`` (a
    receiver bound to PORT), ``udpin:127.0.0.1:PORT`` (wait for the receiver's first packet,
    then answer to it), or a connection from ``sensors.mavlink_link.open_link`` (closed at the end; a
    bound one waits for the receiver as udpin does). ``stop``: a ``threading.Event`` that
    ends the stream early. Returns the report; bounded by ``config.timeout_s`` of wall time."""
    cfg = config
    report = SendReport()
    if isinstance(connect, str):
        conn = open_link(connect, cfg.system, cfg.component)
        listen = connect.startswith("udpin")
    else:
        conn, listen = connect, bool(getattr(connect, "udp_server", False))
    peer = Peer(conn, report)
    rng = np.random.default_rng(cfg.seed)
    junk_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(1)[0])
    rec = Recorder() if cfg.record else None
    t_start = time.monotonic()
    deadline = t_start + cfg.timeout_s
    try:
        if listen:
            end = time.monotonic() + cfg.peer_timeout_s
            while not peer.seen and time.monotonic() < end:
                peer.poll()
                conn.select(0.05)
            if not peer.seen:
                report.timed_out = True
                return report

        held: bytes | None = None           # a data packet held back ...
        passed = False                      # ... and whether an intact packet has left after it

        def write(buf: bytes, intact: bool = True) -> None:
            nonlocal passed
            conn.write(buf)
            report.sent += 1
            passed = passed or (intact and held is not None)

        def control(msg) -> None:
            write(pack(conn, msg))

        sync_every = max(cfg.window // 4, 1)
        next_sync, outstanding = 0, []
        t0_vehicle: float | None = None
        next_heartbeat = -math.inf
        paused = False
        if streams.send_origin:
            o = encode_origin(*streams.origin)
            buf = pack(conn, o)
            write(buf)
            if rec is not None:
                rec.add(buf)
        for tv, stamp, stream, msg in events(streams, cfg):
            now = time.monotonic()
            if now > deadline:
                report.timed_out = True
                break
            if stop is not None and stop.is_set():
                break
            if t0_vehicle is None:
                t0_vehicle = tv
            report.vehicle_s = tv - t0_vehicle
            if tv >= next_heartbeat:
                next_heartbeat = tv + 1.0
                for m in state_messages(cfg, tv):
                    buf = pack(conn, m)
                    write(buf)
                    if rec is not None:
                        rec.add(buf)
            if cfg.pause is not None and not paused and tv >= cfg.pause[0]:
                paused = True
                wait = min(cfg.pause[1], max(deadline - now, 0.0))
                time.sleep(wait)
                report.paused_s += wait
            kinds = stream.split("+")
            if any(k in cfg.skip for k in kinds):
                continue
            if any(a <= tv < a + n and any(k in names for k in kinds) for a, n, names in cfg.outages):
                continue
            if cfg.speed is not None:
                ahead = (tv - t0_vehicle) / cfg.speed - (time.monotonic() - t_start - report.paused_s)
                if ahead > 0:
                    time.sleep(min(ahead, 1.0))
            report.data += 1
            if cfg.junk and junk_rng.random() < cfg.junk:
                conn.write(junk(junk_rng))
                report.junk += 1
            buf = pack(conn, msg)
            u = rng.random(4)
            if u[0] < cfg.loss:
                report.dropped += 1
                continue
            if u[1] < cfg.corrupt and len(buf) > 12:
                b = bytearray(buf)
                b[int(rng.integers(10, len(b)))] ^= 0xFF
                write(bytes(b), intact=False)
                report.corrupted += 1
            elif u[3] < cfg.reorder and held is None:
                held, passed = buf, False
                if rec is not None:
                    rec.add(buf)
                continue
            else:
                if rec is not None:
                    rec.add(buf)
                write(buf)
                if u[2] < cfg.duplicate:
                    write(buf)
                    report.duplicated += 1
                if held is not None:
                    write(held)
                    report.reordered += 1
                    held = None
            if cfg.window:
                if report.data % sync_every == 0:
                    control(mavlink2.MAVLink_timesync_message(0, next_sync))
                    outstanding.append(next_sync)
                    next_sync += 1
                    report.syncs += 1
                peer.poll()
                while outstanding and outstanding[0] <= peer.answered:
                    outstanding.pop(0)
                if len(outstanding) > 4:
                    if not peer.wait(outstanding[0], min(cfg.sync_timeout_s, max(deadline - time.monotonic(), 0))):
                        report.stalls += 1
                        outstanding.clear()
            else:
                peer.poll()
        if held is not None:                 # late only behind an intact packet
            report.reordered += int(passed)
            write(held)
        if cfg.window:                       # everything processed before the report
            control(mavlink2.MAVLink_timesync_message(0, next_sync))
            report.syncs += 1
            if not peer.wait(next_sync, min(cfg.sync_timeout_s, max(deadline - time.monotonic(), 0.0))):
                report.stalls += 1
        end = time.monotonic() + cfg.linger_s
        while time.monotonic() < end:
            peer.poll()
            conn.select(0.02)
    finally:
        report.wall_s = time.monotonic() - t_start
        if rec is not None:
            report.record = rec.frames()
        conn.close()
    return report


def junk(rng: np.random.Generator) -> bytes:
    """A junk datagram: a MAVLink marker byte (1 or 2) and 1 to 40 random bytes."""
    marker = (mavlink2.PROTOCOL_MARKER_V1, mavlink2.PROTOCOL_MARKER_V2)[int(rng.integers(2))]
    return bytes([marker]) + rng.bytes(int(rng.integers(1, 41)))
