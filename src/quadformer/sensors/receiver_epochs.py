"""A receiver's epochs from the stamps of its fixes alone, as they arrive.

A receiver measures its fixes at exact epochs, one period apart; the autopilot stamps each when
its driver reads it, tens of ms later, and that read delay jitters from fix to fix (about 9 ms
std over 30 s on the shared 2014 Pixhawk and Erle-Copter logs, 16 to 18 ms against one line
over a whole Pixhawk flight). A filter that fuses a fix at its stamp
compares it with the IMU's prediction at the wrong instant: every acceleration reads as an
innovation of acceleration x jitter, and a velocity step the detector looks for is blurred by it.
A log carries the receiver's own time of week, from which ``logs.receiver_clock.fix_epochs`` puts
the fixes back at their epochs; a MAVLink link does not (``GPS_RAW_INT.time_usec`` is the
autopilot's stamp). The stamps alone still show the grid:

- each fix is a whole number of periods after the one before: its count is its stamp's place on
  the line below, less half the read delay's spread (where there is no line yet, the interval
  since the previous fix over the median of the last ``PERIOD_FIXES``), within ``SNAP`` of a
  whole number, else the count is lost and the clock starts again from this fix (after a gap
  longer than the window, it starts again without a count lost);
- over the last ``WINDOW_S`` seconds of fixes (at least the last ``MIN_FIXES``: a receiver at
  1 Hz needs 50 s) the stamps lie on a line in that count, plus the read delay, which is never
  negative: the line is the one under every stamp that they lie the least above in sum
  (``lower_line``, an edge of their lower convex hull; its slope follows two clocks whose rates
  differ by a few percent), moved up by the ``LOW_QUANTILE`` of the stamps' lag above it.

``epoch(t)`` restamps a fix at its epoch on the autopilot's clock once ``MIN_FIXES`` fixes are in
the window (before that, where the lags spread over more than ``MAX_SPREAD`` periods, which a
count off by one would show, and where they spread less than ``NO_JITTER_S``, stamps at the
epochs already, the stamp is kept). Restamped fixes are earlier than their arrival
by up to ``allowance`` seconds (the ``HIGH_QUANTILE`` of the lag less its low quantile): a filter
that fuses them at their epoch holds its IMU back that much more (``ResidueStream.hold_s``).
Times out are strictly increasing.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

__all__ = ["ReceiverEpochs"]

PERIOD_FIXES = 50         # intervals whose median is the receiver's period
PERIOD_MIN = 5            # intervals needed before the period is used
SNAP = 0.45               # periods a fix may be off a whole count (on the line, or after the previous fix)
WINDOW_S = 30.0           # s of fixes the line is fitted over
MIN_FIXES = 50            # fixes in the window before a fix is restamped
LOW_QUANTILE = 0.02       # the lag taken as the epochs' offset (the fixes read the soonest)
HIGH_QUANTILE = 0.98      # the lag up to which a late read is still fused at its epoch
MAX_SPREAD = 0.5          # periods the lags may spread over (HIGH - LOW quantile) for a restamp
MIN_STEP = 1e-3           # s, the least step between two times out
NO_JITTER_S = 1e-3        # s, lags spread less than this: the stamps are the epochs, kept as they are


def lower_line(n: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    """(slope, offset) of the line under every point (n increasing) that the points lie the least
    above in sum: a read delay is never negative, so the epochs' line supports the stamps from
    below. The best such line runs along an edge of the points' lower convex hull."""
    hull: list[int] = []
    for i in range(len(n)):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            if (n[b] - n[a]) * (s[i] - s[a]) - (s[b] - s[a]) * (n[i] - n[a]) > 0:
                break
            hull.pop()
        hull.append(i)
    h = np.asarray(hull)
    if len(h) < 2:
        return 0.0, float(s[0])
    slopes = np.diff(s[h]) / np.diff(n[h])
    offsets = s[h[:-1]] - slopes * n[h[:-1]]
    cost = s.sum() - len(s) * offsets - slopes * n.sum()        # the sum of the points' lags above each
    k = int(np.argmin(cost))
    return float(slopes[k]), float(offsets[k])


class ReceiverEpochs:
    """One receiver's epochs from its fixes' stamps (see the module text)."""

    def __init__(self) -> None:
        self.stamps: deque[float] = deque()
        self.counts: deque[int] = deque()
        self.intervals: deque[float] = deque(maxlen=PERIOD_FIXES)
        self.line: tuple[float, float] | None = None   # (offset, slope): the epoch of count n is offset + slope n
        self.last_out = -math.inf
        self.allowance = 0.0          # s, how much earlier than its arrival a fix may be restamped
        self.largest_allowance = 0.0  # s, the largest allowance so far
        self.restamped = 0
        self.restarts = 0
        self.jitter = math.nan        # s, std of the read delay over the window at the last restamp

    def epoch(self, t: float) -> float:
        """The time to fuse the fix stamped ``t`` (s, the autopilot's clock) at."""
        t = float(t)
        if self.stamps and t - self.stamps[-1] > WINDOW_S:     # nothing left to count on: a fresh window
            self._empty()
        if self.stamps:
            n = self._count(t)
            if t > self.stamps[-1]:
                self.intervals.append(t - self.stamps[-1])
            if n is None:
                self._restart()
            else:
                self._add(t, n)
        if not self.stamps:
            self._add(t, 0)
        out = max(self._fit(t), self.last_out + MIN_STEP)
        self.last_out = out
        return out

    def _count(self, t: float) -> int | None:
        """The fix's count of periods: from the fitted line where there is one (the read delay,
        one-sided, is then all the error), else from the interval since the previous fix; None
        where it is not within ``SNAP`` of a whole number after the previous one."""
        if self.line is not None:
            offset, slope = self.line
            x = (t - offset - 0.5 * self.allowance) / slope
        elif len(self.intervals) >= PERIOD_MIN:
            period = float(np.median(self.intervals))
            x = self.counts[-1] + (t - self.stamps[-1]) / period if period > 0 else math.nan
        else:
            return self.counts[-1] + 1
        n = round(x) if math.isfinite(x) else None
        return n if n is not None and n > self.counts[-1] and abs(x - n) <= SNAP else None

    def _add(self, t: float, n: int) -> None:
        self.stamps.append(t)
        self.counts.append(n)
        while len(self.stamps) > MIN_FIXES and self.stamps[0] < t - WINDOW_S:
            self.stamps.popleft()
            self.counts.popleft()

    def _empty(self) -> None:
        self.stamps.clear()
        self.counts.clear()
        self.line = None

    def _restart(self) -> None:
        self._empty()
        self.intervals.clear()
        self.allowance = 0.0
        self.restarts += 1

    def _fit(self, t: float) -> float:
        self.line = None
        self.allowance = 0.0
        if len(self.stamps) < MIN_FIXES:
            return t
        s = np.fromiter(self.stamps, float)
        n = np.fromiter(self.counts, float)
        slope, offset = lower_line(n, s)
        lag = s - (offset + slope * n)                      # the read delays, never negative
        lo, hi = np.quantile(lag, [LOW_QUANTILE, HIGH_QUANTILE])
        if not (slope > 0 and hi - lo <= MAX_SPREAD * slope):
            return t
        self.line = (float(offset + lo), float(slope))
        if hi - lo < NO_JITTER_S:           # stamped at the epochs already (a simulation's, a replayed log's)
            return t
        self.allowance = float(hi - lo)
        self.largest_allowance = max(self.largest_allowance, self.allowance)
        self.jitter = float(np.std(lag))
        self.restamped += 1
        return float(offset + lo + slope * n[-1])

    def note(self) -> str | None:
        """A line on what was done, for the monitor's summary; None before any restamp."""
        if not self.restamped:
            return None
        return (f"gps: {self.restamped} fixes fused at the receiver's epochs found from their stamps (the read "
                f"delay's std over the last window {self.jitter * 1e3:.0f} ms removed; the IMU held back up to "
                f"{self.largest_allowance * 1e3:.0f} ms more for the late reads)"
                + (f"; the count restarted {self.restarts} times" if self.restarts else ""))
