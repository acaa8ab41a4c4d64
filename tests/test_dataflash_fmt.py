"""DataFlash logs whose FMT names fewer columns than its format declares (early ArduPilot logs,
which name four of FMT's five fields): decoded a type at a time, as message by message."""

from __future__ import annotations

import struct

from logs_support import FIX

from quadformer.logs.ardupilot_messages import _indexed_messages, collect_messages


def _fmt_of_fmt(columns: str) -> bytes:
    """An FMT record defining FMT itself (type 0x80, 89 bytes) with the given column names."""
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", 0x80, 89, b"FMT", b"BBnNZ", columns.encode())


def test_an_fmt_naming_four_of_its_five_fields_is_decoded_a_type_at_a_time(tmp_path):
    path = tmp_path / "early.bin"
    path.write_bytes(_fmt_of_fmt("Type,Length,Name,Format") + (FIX / "sim_copter.bin").read_bytes())
    assert _indexed_messages(path, path.stat().st_size) is not None       # no fall back to the slow reader
    fast, slow = collect_messages(path), collect_messages(path, indexed=False)
    assert fast == slow and sum(len(v) for v in fast[0].values()) > 1000
    assert {tuple(r) for r in fast[0]["FMT"]} == {("TimeUS", "Name", "Format")}      # no Columns named
