"""The live link's packets: MAVLink datagrams parsed one by one, and packet loss per sender.

- **Datagrams.** Over UDP every datagram is parsed on its own (``read_datagram``: pymavlink's
  parser starts empty at each datagram). A datagram never carries a partial message over to
  the next, so junk that starts with a marker byte (0xFD, 0xFE) costs its own datagram only
  (one or more ``BAD_DATA``), where a byte-stream parser waits for the bytes its header claims
  and swallows the valid datagrams that follow. Serial and TCP links stay byte streams.
- **Which packets count** (``header``). A packet counts in its sender's sequence when its CRC
  was checked: a message of the dialect. Bytes that fail the check (``BAD_DATA``: junk, or a
  packet damaged on the way) never count, their header being untrustworthy. A well-framed
  message of an id outside the dialect (``UNKNOWN_<id>``; pymavlink cannot check its CRC and
  leaves its header empty) counts by the header read from its bytes, only for a sender already
  followed: it never starts one, so junk that happens to frame such a message counts only when
  its two header bytes name a followed sender (about one random junk datagram in ten million).
- **Loss** (``Sequence``), per sender (system, component), over the 8-bit sequence number:
  **lost** counts the sender's sequence numbers that arrived in no valid packet (dropped on
  the way, or damaged: a damaged packet is a ``BAD_DATA`` besides), **duplicate** the valid
  packets whose number had already arrived, **reordered** the valid packets that arrived after
  a later one. Each sender keeps the state of its last 128 numbers (received, counted lost,
  or not known: before its first packet). A packet d = (seq - last - 1) mod 256 ahead of the
  latest one in order, d < 128, marks the d numbers it skips lost. A packet behind the latest
  (d >= 128, so 0 to 127 behind, all in the window) is a duplicate when its number had
  arrived, else reordered: a number counted lost is taken back out of lost. Time decides
  between the two readings of a step once the sequence may have wrapped: n = dt * rate - 1 -
  m packets are due between the latest packet in order and a stamped packet, dt being the time
  since the sender's reference (its latest stamped packet in order; a stamp is the vehicle time
  of the samples a message carries), rate the sender's packets per second measured over
  ``SENDER_WINDOW_S`` of its stamps without a pause, m the numbers passed since the reference,
  received or lost. When n >= ``GAP_PACKETS`` (half a wrap-around) the packet ends a gap: it is
  ahead by d, and lost += d + 256 k, k >= 0 the number of whole wrap-arounds that brings
  d + 256 k nearest to n (a 510-packet outage is d = 254, k = 1); after a wrap-around every
  number of the window but this one counts lost. Packets without a stamp (HEARTBEAT,
  TIMESYNC) step by the sequence alone; an outage they end is reckoned at the sender's next
  stamped packet. The monitor's own clock plays no part: the time it spends on a message is no
  silence of the link. The sequence cannot tell a sender that paused without advancing it (a
  telemetry link out of transmit space, a played log whose streams all stop for a while) from
  one whose packets were lost: a pause worth more than half a wrap-around of packets reads as
  256 lost per wrap-around. The test sender's report counts alike (``quadformer.sender``).
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass, field

from pymavlink import mavutil

from quadformer.sensors.mavlink import mavlink2

__all__ = ["Reader", "Sequence", "header", "read_datagram"]

MARKERS = (mavlink2.PROTOCOL_MARKER_V1, mavlink2.PROTOCOL_MARKER_V2)
GAP_PACKETS = 128             # packets due beyond the sequence's count for a step to end a gap (half a wrap-around)
SENDER_WINDOW_S = 2.0         # s of a sender's stamps its packet rate is measured over
SENDER_PAUSE_S = 0.5          # s, a pause of a sender's stamps longer than this restarts that window
MAX_SENDERS = 256             # senders whose sequence is followed (MAVLink identities seen)
MISSING, RECEIVED = 1, 2      # a sequence number's state in its sender's window (0: not known)


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


def header(msg) -> tuple[tuple[int, int], int, bool]:
    """(sender (system, component), sequence number, CRC checked) of a parsed message; a
    message of an id outside the dialect (``UNKNOWN_<id>``, its CRC not checked) is read from
    its bytes (MAVLink 1 or 2 framing)."""
    if isinstance(msg, mavlink2.MAVLink_unknown):
        buf = msg.get_msgbuf()
        at = 4 if buf[:1] == bytes([mavlink2.PROTOCOL_MARKER_V2]) else 2
        if len(buf) < at + 3:
            return (0, 0), 0, False
        return (buf[at + 1], buf[at + 2]), buf[at], False
    return (msg.get_srcSystem(), msg.get_srcComponent()), msg.get_seq(), True


class Reader:
    """One message at a time from a pymavlink connection: a UDP connection's datagrams each
    parsed on their own (``read_datagram``), any other link as pymavlink's byte stream."""

    def __init__(self, conn):
        self.conn = conn
        self.udp = isinstance(conn, mavutil.mavudp)
        self.queue: deque = deque()
        self.datagrams = 0

    def recv(self, timeout: float):
        """The next message, waiting up to ``timeout`` s for one; None when none came."""
        if self.queue:
            return self.queue.popleft()
        if not self.udp:
            return self.conn.recv_match(blocking=True, timeout=timeout)
        data = self.conn.recv()              # mavudp.recv also notes the peer a udpin link answers
        if not data and self.conn.select(timeout):
            data = self.conn.recv()
        if not data:
            return None
        self.datagrams += 1
        for m in read_datagram(self.conn.mav, data):
            self.conn.post_message(m)        # pymavlink's own bookkeeping, as its recv_msg does
            self.queue.append(m)
        return self.queue.popleft() if self.queue else None


# -- loss -----------------------------------------------------------------------------------
@dataclass
class _Sender:
    seq: int                          # the latest sequence number in order
    marks: bytearray = field(default_factory=lambda: bytearray(256))   # per number: 0, MISSING, RECEIVED
    stamp: float | None = None        # s, sender time of the reference: its latest stamped packet in order
    since: int = 0                    # sequence numbers passed since the reference (received or lost)
    rate: float | None = None         # packets per second of its stamps
    window: float | None = None       # start of the rate window (sender time)
    count: int = 0                    # packets since


class Sequence:
    """Lost, duplicate and reordered packets per sender, from the sequence numbers read
    together with the senders' stamps (the rule is in the module text)."""

    def __init__(self):
        self.senders: dict[tuple[int, int], _Sender] = {}
        self.counts: Counter = Counter()             # lost, duplicate, reordered

    def packet(self, src: tuple[int, int], seq: int, stamp: float | None, checked: bool = True) -> None:
        """One valid packet from ``src``: its sequence number, the sender time it carries (None:
        none) and whether its CRC was checked (an unchecked one counts only for a sender
        already followed)."""
        s = self.senders.get(src)
        if s is None:
            if not checked:
                return
            if len(self.senders) >= MAX_SENDERS:
                self.senders.pop(next(iter(self.senders)))
            s = self.senders[src] = _Sender(seq)
            s.marks[seq] = RECEIVED
            self._rate(s, stamp)
            return
        d = (seq - s.seq - 1) % 256
        due = -math.inf                             # packets due between the latest in order and this one
        if s.rate and stamp is not None and s.stamp is not None:
            due = (stamp - s.stamp) * s.rate - 1.0 - s.since
        if due >= GAP_PACKETS:
            self._forward(s, seq, d, max(0, math.floor((due - d) / 256 + 0.5)))
        elif d >= 128:                              # behind the latest: 0 to 127 back, in the window
            mark = s.marks[seq]
            if mark == RECEIVED:
                self.counts["duplicate"] += 1
                return
            self.counts["reordered"] += 1
            if mark == MISSING:                     # counted lost when it was skipped: not lost after all
                self.counts["lost"] -= 1
            s.marks[seq] = RECEIVED
            return
        else:
            self._forward(s, seq, d, 0)
        self._rate(s, stamp)

    def _forward(self, s: _Sender, seq: int, d: int, wraps: int) -> None:
        """``seq``, d numbers after the latest plus ``wraps`` whole wrap-arounds: the numbers
        skipped are lost (after a wrap-around, every number of the window)."""
        self.counts["lost"] += d + 256 * wraps
        if wraps:
            s.marks[:] = bytes([MISSING]) * 256
        else:
            for k in range(1, d + 1):
                s.marks[(s.seq + k) % 256] = MISSING
        s.marks[seq] = RECEIVED
        s.seq = seq
        s.since += d + 1

    @staticmethod
    def _rate(s: _Sender, stamp: float | None) -> None:
        """The sender's packet rate over windows of its stamps, and its reference; a stamp a
        little older than the reference (a GPS fix stamped when it was measured) counts the
        packet and moves nothing."""
        s.count += 1
        if stamp is None or (s.stamp is not None and 0.0 <= s.stamp - stamp <= SENDER_PAUSE_S):
            return
        if s.window is None or s.stamp is None or not 0.0 < stamp - s.stamp <= SENDER_PAUSE_S:
            s.window, s.count = stamp, 0             # the first stamp, a pause, a clock going back
        elif stamp - s.window >= SENDER_WINDOW_S:
            s.rate = s.count / (stamp - s.window)
            s.window, s.count = stamp, 0
        s.stamp, s.since = stamp, 0
