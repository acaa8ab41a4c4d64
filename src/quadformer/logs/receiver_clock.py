"""The receiver's clock in a log: fixes stamped at their epochs, and the receiver's latency.

- **Epochs.** An autopilot logs each fix when its driver read it: the stamp carries the
  receiver's output latency and the driver's scheduling, which jitter by 10 to 100 ms from one
  fix to the next on real logs, where the receiver's own time of the fix (GPS time of week,
  ArduPilot's ``GPS.TimeMS``/``GMS``, PX4's ``time_utc_usec``) steps by exactly its interval.
  A test that compares a fix with the one before it (the receiver's consistency: position
  change against velocity x interval; the IMU's velocity change over the interval) reads that
  jitter as a position or velocity error of speed x jitter (0.3 m at 7 m/s and 40 ms).
  ``fix_epochs`` stamps each fix at its epoch on the autopilot's clock: a line fitted through
  (time of week, stamp), its slope the median of the slopes between fixes ``PAIR_S`` apart (the
  two clocks' rates may differ: some boards' clocks run several percent slow against GPS time,
  and the fit follows them), its offset the ``LOW_QUANTILE`` of the stamps' lag behind the line
  (the fixes read the soonest), so the fixes keep the autopilot's time base and lose only the
  jitter. A fix read more than ``MAX_SHIFT_S`` after its epoch keeps its stamp, or, where that
  stamp falls out of order with its neighbours' epochs (a start-up burst of buffered fixes read
  at once), is dropped as stale. Without a usable time of week (fewer than ``MIN_FIXES``, not
  increasing) the stamps stay as logged.
- **Latency.** A fix is measured before the autopilot reads it (PX4's ``EKF2_GPS_DELAY``,
  ArduPilot's ``GPS_DELAY_MS``, ``EK2_GPS_DELAY``, ``EKF_POS_DELAY``); a filter that fuses it at
  its stamp compares a lagged velocity with the IMU's, and every change of acceleration shows in
  the innovation as that change x the latency. Where neither the filter's configuration nor the
  log gives it, ``latency`` estimates it from the log itself, without a filter
  (``estimator.latency``: the D that makes the velocity steps the IMU did not feel, over each GPS
  interval in the air, the least spread; ``velocity_steps`` gives them for a log). A live link's
  latency is estimated the same way from its samples (``estimator.latency.LatencyEstimator``).
  On two 90 s simulated flights written with a 150 ms latency and a
  40 ms read jitter it finds 150 and 170 ms; on the shared Erle-Copter flights, whose EKF states
  220 ms, 110 to 350 ms (median 215 ms over 10 flights, none on 6 others).
"""

from __future__ import annotations

import numpy as np

from quadformer.estimator.latency import LATENCY_GRID, pick_latency, robust_std
from quadformer.sensors.receiver_epochs import LOW_QUANTILE, NO_JITTER_S   # the lag taken as the epochs' offset;
                                                                         # stamps this close to them are kept

__all__ = ["fix_epochs", "latency", "velocity_steps", "week_seconds"]

WEEK_S = 604800.0
MIN_FIXES = 20             # fixes with a time of week needed to fit the epochs
PAIR_S = 30.0              # s of time of week between the fixes whose slopes make the fit's slope
MAX_SHIFT_S = 0.5          # s, the most a fix may move from its stamp
MAX_SLOPE_ERR = 0.15       # the two clocks' rates may differ by this fraction at most


def week_seconds(week: np.ndarray, ms_of_week: np.ndarray) -> np.ndarray:
    """GPS time in seconds (week x 604800 + time of week) of fixes; NaN where the receiver gave
    no time (week 0 or a time of week of 0)."""
    week, ms = np.asarray(week, dtype=float), np.asarray(ms_of_week, dtype=float)
    out = week * WEEK_S + ms * 1e-3
    return np.where((week > 0) & (ms > 0) & np.isfinite(out), out, np.nan)


def fix_epochs(t: np.ndarray, tow: np.ndarray) -> tuple[np.ndarray, np.ndarray, str | None]:
    """(stamps, keep, note): the fixes' stamps ``t`` (s, the autopilot's clock, increasing)
    moved to their epochs from the receiver's time ``tow`` (s, NaN where unknown; see the module
    text), and which fixes to keep: a fix whose time of week repeats the previous one's is the
    same fix read again, dropped. ``t`` unchanged, every fix kept and note None where the time of
    week cannot be used."""
    t = np.asarray(t, dtype=float)
    tow = np.asarray(tow, dtype=float)
    every = np.ones(len(t), dtype=bool)
    keep = every.copy()
    keep[1:] = ~(tow[1:] == tow[:-1])
    ok = np.isfinite(tow) & np.isfinite(t) & keep
    if ok.sum() < MIN_FIXES:
        return t, every, None
    tt, ww = t[ok], tow[ok]
    if np.any(np.diff(ww) <= 0) or ww[-1] - ww[0] < PAIR_S:
        return t, every, None
    j = np.searchsorted(ww, ww + PAIR_S)
    i = np.nonzero(j < len(ww))[0]
    slope = float(np.median((tt[j[i]] - tt[i]) / (ww[j[i]] - ww[i])))
    if not abs(slope - 1.0) <= MAX_SLOPE_ERR:
        return t, every, None
    lag = tt - slope * ww
    offset = float(np.quantile(lag, LOW_QUANTILE))
    new = t.copy()
    near = ok.copy()
    near[ok] = np.abs(offset + slope * ww - tt) <= MAX_SHIFT_S     # a fix read long after its epoch keeps its stamp
    new[near] = offset + slope * tow[near]
    # a kept stamp out of order with its neighbours' epochs (a start-up burst of buffered fixes
    # read at once) is stale: dropped
    again = int((~keep).sum())                         # fixes read twice
    stale = 0
    at = np.nonzero(near)[0]                           # the restamped fixes, in order
    for k in np.nonzero(ok & ~near)[0]:
        j = np.searchsorted(at, k)
        before = new[at[j - 1]] if j > 0 else -np.inf
        after = new[at[j]] if j < len(at) else np.inf
        if not before < new[k] < after:
            keep[k] = False
            stale += 1
    if near.sum() < MIN_FIXES or np.any(np.diff(new[keep]) <= 0):
        return t, every, None
    dev = lag[near[ok]] - offset
    jitter = float(np.std(dev - np.median(dev)))
    rate = f"; the autopilot's clock runs {abs(slope - 1) * 100:.1f}% {'slow' if slope < 1 else 'fast'} " \
           "against GPS time" if abs(slope - 1.0) > 2e-3 else ""
    late = int(ok.sum() - near.sum()) - stale
    if jitter < NO_JITTER_S and abs(slope - 1.0) <= 2e-3 and not late:     # stamped at the epochs already
        return t, keep, (f"gps: {again} fixes read twice (the same time of week) dropped" if again else None)
    return new, keep, (f"gps: {int(near.sum())} fixes stamped at the receiver's epochs (GPS time of week), "
                 f"the logged stamps' jitter {jitter * 1e3:.0f} ms std removed{rate}"
                 + (f"; {late} read more than {MAX_SHIFT_S:g} s after their epoch keep their stamps" if late else "")
                 + (f"; {stale} read more than {MAX_SHIFT_S:g} s after their epoch and out of order with the "
                    "others' epochs dropped (stale)" if stale else "")
                 + (f"; {again} fixes read twice (the same time of week) dropped" if again else ""))


def imu_velocity(log):
    """(fix times, fix horizontal velocities, IMU times, the IMU's horizontal velocity integrated
    in the world through the autopilot's attitude) of ``log``; None without the streams."""
    from quadformer.geometry.frames import quat_rotate

    g, imu, att = log.gps, log.imu, log.attitude
    if g is None or imu is None or att is None or len(g) < 10 or len(imu) < 10 or len(att) < 2:
        return None
    ti = imu["t"].to_numpy(dtype=float)
    ta = att["t"].to_numpy(dtype=float)
    q = att[["qx", "qy", "qz", "qw"]].to_numpy(dtype=float)
    j = np.clip(np.searchsorted(ta, ti), 0, len(ta) - 1)
    aw = quat_rotate(q[j], imu[["ax", "ay", "az"]].to_numpy(dtype=float))[:, :2]
    cum = np.concatenate([[np.zeros(2)], np.cumsum(0.5 * (aw[1:] + aw[:-1]) * np.diff(ti)[:, None], axis=0)])
    return g["t"].to_numpy(dtype=float), g[["vx", "vy"]].to_numpy(dtype=float), ti, cum


def velocity_steps(log, air: np.ndarray | None = None, delay: float = 0.0, _pre=None,
                   every: bool = False) -> np.ndarray | None:
    """Per GPS interval of ``log`` in the air (``air``: a flag per fix; default every fix) whose
    fixes are one interval apart and inside the IMU's span, the horizontal velocity change of the
    receiver minus the IMU's over the interval ``delay`` seconds earlier (the specific force through
    the autopilot's attitude, integrated; gravity is vertical), (n, 2); None without GPS, IMU and
    the autopilot's attitude, or with fewer than 30 such intervals. ``every``: a row per interval
    of the log (fixes - 1), NaN where the interval is not one of those."""
    pre = imu_velocity(log) if _pre is None else _pre
    if pre is None:
        return None
    t, v, ti, cum = pre
    air = np.ones(len(t), bool) if air is None else np.asarray(air, bool)
    dt = np.diff(t)
    step = float(np.median(dt)) if len(dt) else 0.0
    ok = (air[1:] & air[:-1] & (dt > 0) & (dt <= 1.5 * step) & (t[:-1] - LATENCY_GRID[-1] >= ti[0])
          & (t[1:] <= ti[-1]) & np.isfinite(v).all(axis=1)[1:] & np.isfinite(v).all(axis=1)[:-1])
    if ok.sum() < 30:
        return None
    at = np.stack([np.interp(t - delay, ti, cum[:, k]) for k in range(2)], axis=1)
    e = np.diff(v, axis=0) - np.diff(at, axis=0)
    if every:
        return np.where(ok[:, None], e, np.nan)
    return e[ok]


def latency_steps(log, air: np.ndarray | None = None,
                  every: bool = False) -> tuple[float | None, np.ndarray | None]:
    """(latency s or None, the velocity steps at it; None without the data): the receiver latency
    that the log's own IMU and GPS show (``estimator.latency``; None where it does not narrow the
    spread by ``MIN_GAIN``, the steps then those at 0) and ``velocity_steps`` there (``every``: a
    row per interval), the IMU integrated once for both."""
    pre = imu_velocity(log)
    spread = []
    for d in LATENCY_GRID:
        e = velocity_steps(log, air, float(d), pre)
        if e is None:
            return None, None
        spread.append(robust_std(e))
    best = pick_latency(spread)
    return best, velocity_steps(log, air, best or 0.0, pre, every=every)


def latency(log, air: np.ndarray | None = None) -> tuple[float | None, float | None]:
    """(latency s or None, the velocity residual's robust std at it, m/s; None without the data):
    ``latency_steps``' latency and its steps' spread."""
    best, e = latency_steps(log, air)
    return best, (None if e is None else robust_std(e))
