"""The live link's packets: MAVLink datagrams parsed one by one, and packet loss per sender.

- **Datagrams.** Over UDP every datagram is parsed on its own (``read_datagram``: pymavlink's
  parser starts empty at each datagram). A datagram never carries a partial message over to
  the next, so junk that starts with a marker byte (0xFD, 0xFE) costs its own datagram only
  (one ``BAD_DATA``), where a byte-stream parser waits for the bytes its header claims and
  swallows the valid datagrams that follow. Serial and TCP links stay byte streams.
- **Loss** (``Sequence``), per sender: the forward step of the 8-bit sequence number,
  d = (seq - last - 1) mod 256, read together with time. The packets due in the step are
  n = dt * rate - 1, with dt the time since the sender's last stamp for a packet that carries
  one (the vehicle time of the samples in its message), else the time between this monitor
  reading the sender's previous packet and this one (HEARTBEAT, TIMESYNC); rate is the
  sender's packets per second, measured over ``SENDER_WINDOW_S`` of its stamps without a
  pause. When n >= ``GAP_PACKETS`` (half a wrap-around) the packet ends a gap:
  lost += d + 256 k, k >= 0 the number of whole wrap-arounds that brings the sequence's count
  nearest to n (a 510-packet outage is d = 254, k = 1). Otherwise the sequence decides alone:
  d = 255 is a duplicate, 128..254 a packet that arrived after later ones (reordered, counted
  lost when it was skipped and no longer), else d packets lost. The sequence cannot tell a
  sender that paused without advancing it (a telemetry link out of transmit space) from one
  whose packets were lost: a pause worth more than half a wrap-around of packets reads as
  256 lost.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Callable

from pymavlink import mavutil

from quadformer.sensors.mavlink import mavlink2

__all__ = ["Reader", "Sequence", "read_datagram"]

MARKERS = (mavlink2.PROTOCOL_MARKER_V1, mavlink2.PROTOCOL_MARKER_V2)
GAP_PACKETS = 128             # packets due beyond which a sequence step ends a gap (half a wrap-around)
SENDER_WINDOW_S = 2.0         # s of a sender's stamps its packet rate is measured over
SENDER_PAUSE_S = 0.5          # s, a pause of a sender's stamps longer than this restarts that window
MAX_SENDERS = 256             # senders whose sequence is followed (MAVLink identities seen)


# -- datagrams ------------------------------------------------------------------------------
def _reset(mav) -> None:
    """pymavlink's parser back between messages (the state ``MAVLink.__init__`` sets)."""
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = mavlink2.HEADER_LEN_V1 + 2
    mav.have_prefix_error = False


def read_datagram(mav, data: bytes) -> list:
    """The messages of one datagram, parsed on their own by ``mav`` (robust parsing: bad CRCs
    and junk are ``BAD_DATA``). A header claiming more bytes than the datagram has left is one
    ``BAD_DATA``, and parsing resumes at the next marker byte after it."""
    out: list = []
    rest = bytes(data)
    while rest:
        _reset(mav)
        m = mav.parse_char(rest)
        while m is not None:
            out.append(m)
            m = mav.parse_char(b"")
        tail = bytes(mav.buf[mav.buf_index:])
        if not tail:
            break
        cut = next((i for i in range(1, len(tail)) if tail[i] in MARKERS), len(tail))
        out.append(mavlink2.MAVLink_bad_data(bytearray(tail[:cut]), "truncated at the end of a datagram"))
        rest = tail[cut:]
    _reset(mav)
    return out


class Reader:
    """One message at a time from a pymavlink connection: a UDP connection's datagrams each
    parsed on their own (``read_datagram``), any other link as pymavlink's byte stream.
    ``read_at``: the clock when the message in hand was read off the link."""

    def __init__(self, conn, clock: Callable[[], float] = time.monotonic):
        self.conn, self.clock = conn, clock
        self.udp = isinstance(conn, mavutil.mavudp)
        self.queue: deque = deque()
        self.datagrams = 0
        self.read_at = clock()

    def recv(self, timeout: float):
        """The next message, waiting up to ``timeout`` s for one; None when none came."""
        if self.queue:
            return self.queue.popleft()
        if not self.udp:
            m = self.conn.recv_match(blocking=True, timeout=timeout)
            self.read_at = self.clock()
            return m
        data = self.conn.recv()              # mavudp.recv also notes the peer a udpin link answers
        if not data and self.conn.select(timeout):
            data = self.conn.recv()
        if not data:
            return None
        self.read_at = self.clock()
        self.datagrams += 1
        for m in read_datagram(self.conn.mav, data):
            self.conn.post_message(m)        # pymavlink's own bookkeeping, as its recv_msg does
            self.queue.append(m)
        return self.queue.popleft() if self.queue else None


# -- loss -----------------------------------------------------------------------------------
@dataclass
class _Sender:
    seq: int
    wall: float                       # the clock when its last in-order packet was read
    stamp: float | None = None        # s, sender time of its last stamped in-order packet
    rate: float | None = None         # packets per second of its stamps
    window: float | None = None       # start of the rate window (sender time)
    count: int = 0                    # packets since


class Sequence:
    """Lost, duplicate and reordered packets per sender, from the sequence numbers read
    together with time (the rule is in the module text)."""

    def __init__(self):
        self.senders: dict[tuple[int, int], _Sender] = {}
        self.counts: Counter = Counter()             # lost, duplicate, reordered

    def packet(self, src: tuple[int, int], seq: int, stamp: float | None, now: float) -> None:
        """One packet from ``src``: its sequence number, the sender time it carries (None:
        none) and the clock when it was read."""
        s = self.senders.get(src)
        if s is None:
            if len(self.senders) >= MAX_SENDERS:
                self.senders.pop(next(iter(self.senders)))
            s = self.senders[src] = _Sender(seq, now)
            self._rate(s, stamp)
            return
        d = (seq - s.seq - 1) % 256
        due = None
        if s.rate and stamp is not None and s.stamp is not None:
            due = (stamp - s.stamp) * s.rate - 1.0
        elif s.rate and stamp is None:
            due = (now - s.wall) * s.rate - 1.0
        gap = due is not None and due >= GAP_PACKETS
        if gap:
            self.counts["lost"] += d + 256 * max(0, round((due - d) / 256))
        elif d == 255:
            self.counts["duplicate"] += 1
            return
        elif d >= 128:                              # arrived after a later one: counted lost then, not now
            self.counts["reordered"] += 1
            self.counts["lost"] = max(self.counts["lost"] - 1, 0)
            return
        else:
            self.counts["lost"] += d
        s.seq, s.wall = seq, now
        if gap and stamp is None:
            s.stamp = None                          # counted: its stamps start again from the next one
        self._rate(s, stamp)

    @staticmethod
    def _rate(s: _Sender, stamp: float | None) -> None:
        """The sender's packet rate over windows of its stamps; a stamp a little older than the
        last (a GPS fix stamped when it was measured) counts the packet and moves nothing."""
        s.count += 1
        if stamp is None or (s.stamp is not None and 0.0 <= s.stamp - stamp <= SENDER_PAUSE_S):
            return
        if s.window is None or s.stamp is None or not 0.0 < stamp - s.stamp <= SENDER_PAUSE_S:
            s.window, s.count = stamp, 0             # the first stamp, a pause, a clock going back
        elif stamp - s.window >= SENDER_WINDOW_S:
            s.rate = s.count / (stamp - s.window)
            s.window, s.count = stamp, 0
        s.stamp = stamp
