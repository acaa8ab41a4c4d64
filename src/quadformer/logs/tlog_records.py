"""The records of a MAVLink telemetry log read at once, for ``tlog.read_tlog``: where every record
is a receive time and a whole MAVLink packet (1 or 2) with a valid checksum (a ground station's
log as it usually is), the framing and the checksums are checked with numpy and only the messages
of the types wanted are decoded, by pymavlink's own ``decode`` and stamped as its log reader
stamps them; anything else (a bad checksum, bytes between packets, a record cut short, flags
pymavlink refuses) is left to pymavlink's reader, message by message. The messages are those
pymavlink's reader gives, in file order."""

from __future__ import annotations

import sys
from collections.abc import Collection

import numpy as np

__all__ = ["whole_messages"]

_STAMP = 8                          # bytes of a record's receive time (UNIX microseconds, big-endian)
_V1, _V2 = 0xFE, 0xFD               # MAVLink 1 and 2 start bytes
_HEADER = {_V1: 6, _V2: 10}         # start byte to message id, per protocol
_CRC = 2
_SIGNED, _SIGNATURE = 0x01, 13      # MAVLink 2: the incompatibility flag of a signed packet, its signature


def whole_messages(data: bytes, mav, types: Collection[str]) -> tuple[int, list] | None:
    """(number of records, the messages of ``types`` in file order) of a tlog's bytes ``data``
    whose records are all whole MAVLink packets with valid checksums; None otherwise. ``mav``:
    the pymavlink parser (``mavlink_connection(...).mav``) whose ``decode`` makes the messages."""
    framed = _framing(data)
    if framed is None:
        return None
    pkt, header, size = framed
    known = sys.modules[type(mav).__module__].mavlink_map
    buf = np.frombuffer(data, dtype=np.uint8)
    length = buf[pkt + 1].astype(np.int64)
    v2 = header == _HEADER[_V2]
    msgid = np.where(v2, buf[pkt + 7].astype(np.int64) | (buf[pkt + 8].astype(np.int64) << 8)
                     | (buf[pkt + 9].astype(np.int64) << 16), buf[pkt + 5].astype(np.int64))
    ids, which = np.unique(msgid, return_inverse=True)
    extra = np.array([known[i].crc_extra if i in known else -1 for i in ids.tolist()], dtype=np.int64)[which]
    body = header - 1 + length                       # the checksummed bytes: length byte to payload's end
    checked = extra >= 0                             # pymavlink decodes an unknown id without its checksum
    for n in np.unique(body[checked]).tolist():
        rows = np.flatnonzero(checked & (body == n))
        at = pkt[rows]
        crc = _x25(buf[at[:, None] + 1 + np.arange(n)], extra[rows])
        stored = buf[at + 1 + n].astype(np.int64) | (buf[at + 2 + n].astype(np.int64) << 8)
        if not np.array_equal(crc, stored):
            return None
    taken = [i for i in ids.tolist() if i in known and known[i].msgname in types]
    out = []
    for k in np.flatnonzero(np.isin(msgid, taken)).tolist():
        p = int(pkt[k])
        m = mav.decode(bytearray(data[p:p + int(size[k])]))
        usec = int.from_bytes(data[p - _STAMP:p], "big")
        m._posted = True                               # as pymavlink's log reader stamps a message
        m._timestamp = usec * 1.0e-6
        m._link = usec & 0x3
        out.append(m)
    return len(pkt), out


def _framing(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(packet offsets, header lengths, packet sizes) when the file is records back to back to
    its end, each a receive time and a MAVLink packet pymavlink takes whole; else None."""
    pkts, headers, sizes = [], [], []
    pos, end = 0, len(data)
    ahead = _HEADER[_V1] + _CRC          # what pymavlink's parser reads of a packet before its length
    while pos < end:
        p = pos + _STAMP
        if p + 3 > end:
            return None
        magic = data[p]
        header = _HEADER.get(magic)
        if header is None:
            return None
        size = header + data[p + 1] + _CRC
        if magic == _V2:
            flags = data[p + 2]
            if flags & ~_SIGNED:
                return None                            # pymavlink refuses it: bad data
            size += _SIGNATURE if flags & _SIGNED else 0
        if p + size > end or size < ahead:
            return None                                # cut short, or read into the next record by pymavlink
        ahead = header + _CRC
        pkts.append(p)
        headers.append(header)
        sizes.append(size)
        pos = p + size
    return np.array(pkts, dtype=np.int64), np.array(headers, dtype=np.int64), np.array(sizes, dtype=np.int64)


def _x25(body: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """MAVLink's checksum (CRC-16/MCRF4XX) of each row of ``body`` followed by its ``extra``
    byte, all rows at once."""
    crc = np.full(len(body), 0xFFFF, dtype=np.int64)
    for col in [*body.T.astype(np.int64), extra]:
        tmp = col ^ (crc & 0xFF)
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = (crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)
    return crc
