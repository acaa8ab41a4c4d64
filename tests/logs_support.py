"""Helpers shared by the flight-log tests."""

from __future__ import annotations

import contextlib
import signal
from pathlib import Path

FIX = Path(__file__).parent / "fixtures" / "logs"


class TimeLimit(BaseException):
    """Raised by ``time_limit``; a BaseException, so that no ``except Exception`` in a
    library or a reader can swallow it."""


@contextlib.contextmanager
def time_limit(seconds: float):
    """Fail the block if it runs longer than ``seconds`` (SIGALRM: main thread, POSIX)."""
    def expire(signum, frame):
        raise TimeLimit(f"still running after {seconds} s")
    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def write_dataflash(path: Path, formats: dict[str, tuple[str, str]], messages: list[tuple[str, list]]) -> Path:
    """A DataFlash file written from scratch: ``formats`` {name: (struct characters, columns)},
    one FMT message each, then ``messages`` [(name, values)] in order, packed by pymavlink's own
    format table (``DFFormat``; 'L' latitudes as int 1e-7 deg)."""
    import struct

    from pymavlink import DFReader

    out = bytearray()
    fmts = {}
    for k, (name, (chars, columns)) in enumerate(formats.items()):
        fmt = DFReader.DFFormat(0x81 + k, name, 0, chars, columns)
        fmts[name] = fmt
        out += struct.pack("<BBBBB4s16s64s", 0xA3, 0x95, 0x80, fmt.type, struct.calcsize(fmt.msg_struct) + 3,
                           name.encode(), chars.encode(), columns.encode())
    for name, values in messages:
        out += struct.pack("<BBB", 0xA3, 0x95, fmts[name].type) + struct.pack(fmts[name].msg_struct, *values)
    path.write_bytes(bytes(out))
    return path
