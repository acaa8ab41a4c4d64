"""The receiver's latency from the vehicle's own IMU and GPS, without a filter.

A fix is measured before the autopilot reads it; a filter that fuses it at its stamp compares a
lagged velocity with the IMU's, and every change of acceleration shows in the innovation as
that change x the latency (at a brisk manoeuvre more than a consistent drift's onset does). Over
each GPS interval in the air, the receiver's horizontal velocity change minus the IMU's specific
force rotated to the world by the autopilot's attitude and integrated over the same interval
taken D earlier is the velocity step the IMU did not feel; the latency is the D of
``LATENCY_GRID`` that makes those steps the least spread (their robust std, smoothed over three
neighbouring D, the least refined by a parabola), kept where it narrows the spread at D = 0 by
``MIN_GAIN`` (a flight without manoeuvres tells nothing).

``pick_latency`` is that choice from the spreads; a log's whole record goes through
``logs.receiver_clock.latency``, a live link's samples through ``LatencyEstimator`` one at a
time (the monitor estimates its link's latency in the first minute in the air and restarts its
filter with it).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from quadformer.geometry.frames import quat_rotate

__all__ = ["LATENCY_GRID", "MIN_GAIN", "LatencyEstimator", "pick_latency", "robust_std"]

LATENCY_GRID = np.round(np.arange(0.0, 0.401, 0.02), 2)   # s
MIN_GAIN = 0.05            # the least fractional narrowing of the spread a latency must bring


def robust_std(e: np.ndarray) -> float:
    """1.4826 x the median absolute deviation of all of ``e``'s values about their column medians."""
    return float(1.4826 * np.median(np.abs(e - np.median(e, axis=0))))


def pick_latency(spread) -> float | None:
    """The latency (s) whose velocity steps are the least spread (``spread``: their robust std at
    each D of ``LATENCY_GRID``), or None where none narrows the spread at 0 by ``MIN_GAIN``."""
    s = np.asarray(spread, dtype=float)
    if len(s) != len(LATENCY_GRID) or not np.isfinite(s).all():
        raise ValueError(f"latency: one finite spread per latency of the grid ({len(LATENCY_GRID)}), got {s!r}")
    # the spread against D is noisy (a few percent from one D to the next): smoothed over three
    # neighbours, its least value refined by a parabola through it and its two neighbours
    padded = np.concatenate([[s[0]], s, [s[-1]]])
    sm = 0.25 * padded[:-2] + 0.5 * padded[1:-1] + 0.25 * padded[2:]
    k = int(np.argmin(sm))
    if k == 0 or sm[k] > (1.0 - MIN_GAIN) * sm[0]:
        return None
    best = float(LATENCY_GRID[k])
    if k < len(sm) - 1:
        a, b, c = sm[k - 1], sm[k], sm[k + 1]
        curve = a - 2.0 * b + c
        if curve > 0:
            best += 0.5 * (a - c) / curve * float(LATENCY_GRID[1] - LATENCY_GRID[0])
    return round(float(best), 2)


class LatencyEstimator:
    """The latency online, from a link's samples in time order: ``attitude(t, q)`` (xyzw, FLU
    body -> ENU world), ``imu(t, f)`` (specific force, FLU, m/s^2), ``fix(t, vel, air)`` (ENU
    velocity; ``air``: the vehicle is flying). ``estimate()`` gives the latency (s, or None)
    once ``min_intervals`` GPS intervals in the air are in, as ``logs.receiver_clock.latency``
    finds it on a log (the IMU's horizontal specific force through the latest attitude,
    integrated by the trapezoid rule; an IMU sample more than ``ATTITUDE_S`` after the latest
    attitude is not, and the fixes that would need it are not taken: a link that sends its
    attitude once, or stops sending it, tells nothing of the latency). At most ``max_intervals``
    are kept (the latest)."""

    HISTORY_S = float(LATENCY_GRID[-1]) + 1.0     # s of integrated IMU kept for the fixes to look back on
    MAX_PENDING = 20                              # fixes waiting for the IMU to reach them
    ATTITUDE_S = 0.5                              # s an attitude turns the IMU samples after it

    def __init__(self, min_intervals: int = 150, max_intervals: int = 3000):
        if not (isinstance(min_intervals, int) and 30 <= min_intervals <= max_intervals):
            raise ValueError(f"latency: min_intervals must be an integer from 30 to max_intervals "
                             f"({max_intervals!r}), got {min_intervals!r}")
        self.min_intervals, self.max_intervals = min_intervals, max_intervals
        self._q: np.ndarray | None = None
        self._q_t = -math.inf
        self._imu: deque[tuple[float, np.ndarray]] = deque()    # (t, integrated horizontal velocity)
        self._last: tuple[float, np.ndarray] | None = None       # the previous IMU sample (t, world acc)
        self._cum = np.zeros(2)
        self._prev: tuple[float, np.ndarray, np.ndarray, bool] | None = None   # the previous fix
        self._dts: deque[float] = deque(maxlen=50)
        self._pending: deque[tuple[float, np.ndarray, bool]] = deque()   # fixes the IMU has not reached
        self.steps: deque[np.ndarray] = deque(maxlen=max_intervals)   # per interval, (grid, 2)
        self.taken = 0                                                # intervals taken in all

    def attitude(self, t: float, q) -> None:
        q = np.asarray(q, dtype=float)
        if q.shape == (4,) and np.isfinite(q).all() and np.linalg.norm(q) > 0.5:
            self._q, self._q_t = q / np.linalg.norm(q), t

    def imu(self, t: float, f) -> None:
        f = np.asarray(f, dtype=float)[:3]
        if self._q is None or not (math.isfinite(t) and np.isfinite(f).all()):
            return
        if t - self._q_t > self.ATTITUDE_S:          # no recent attitude: the integral starts again
            self._imu.clear()
            self._last = self._prev = None
            return
        a = quat_rotate(self._q[None, :], f[None, :])[0, :2]
        if self._last is not None:
            dt = t - self._last[0]
            if dt <= 0:
                return
            self._cum = self._cum + 0.5 * (a + self._last[1]) * dt
        self._last = (t, a)
        self._imu.append((t, self._cum.copy()))
        while self._imu and self._imu[0][0] < t - self.HISTORY_S:
            self._imu.popleft()
        self._resolve()

    def _at(self, times: np.ndarray) -> np.ndarray | None:
        """The integrated horizontal velocity at ``times`` (interpolated), or None where the kept
        IMU does not span them."""
        if len(self._imu) < 2:
            return None
        ti = np.array([s[0] for s in self._imu])
        if times.min() < ti[0] or times.max() > ti[-1]:
            return None
        cum = np.array([s[1] for s in self._imu])
        return np.stack([np.interp(times, ti, cum[:, k]) for k in range(2)], axis=1)

    def fix(self, t: float, vel, air: bool) -> None:
        """A fix at ``t``; taken in once the IMU has reached ``t``."""
        v = np.asarray(vel, dtype=float)[:2]
        if math.isfinite(t):
            self._pending.append((t, v, bool(air)))
            self._resolve()

    def _resolve(self) -> None:
        while self._pending and self._imu and self._pending[0][0] <= self._imu[-1][0]:
            t, v, air = self._pending.popleft()
            at = self._at(t - LATENCY_GRID) if np.isfinite(v).all() else None
            prev, self._prev = self._prev, (None if at is None else (t, v, at, air))
            if prev is None or at is None or t <= prev[0]:
                continue
            dt = t - prev[0]
            step = float(np.median(self._dts)) if self._dts else dt
            self._dts.append(dt)
            if air and prev[3] and dt <= 1.5 * step:
                self.steps.append((v - prev[1])[None, :] - (at - prev[2]))
                self.taken += 1
        while len(self._pending) > self.MAX_PENDING:       # an IMU that stopped: the oldest fixes go
            self._pending.popleft()
            self._prev = None

    @property
    def intervals(self) -> int:
        """GPS intervals in the air taken so far (at most ``max_intervals``)."""
        return len(self.steps)

    def estimate(self) -> float | None:
        """The latency (s) the intervals so far show, or None (too few of them, or no latency
        narrows the spread by ``MIN_GAIN``)."""
        if len(self.steps) < self.min_intervals:
            return None
        e = np.stack(self.steps)                                    # (n, grid, 2)
        return pick_latency([robust_std(e[:, j, :]) for j in range(len(LATENCY_GRID))])
