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
