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
  jitter. Without a usable time of week (fewer than ``MIN_FIXES``, not increasing, or a
  restamped fix further than ``MAX_SHIFT_S`` from its stamp) the stamps stay as logged.
- **Latency.** A fix is measured before the autopilot reads it (PX4's ``EKF2_GPS_DELAY``,
  ArduPilot's ``GPS_DELAY_MS``); a filter that fuses it at its stamp compares a lagged velocity
  with the IMU's, and every acceleration shows in the innovation as acceleration x latency.
  Where neither the filter's configuration nor the log gives it, ``latency`` estimates it from a
  replay fused without one: the delay D that makes the fix-to-fix change of GPS velocity minus
  the IMU's velocity change over the interval (the filter's propagation) the least spread,
  grid ``LATENCY_GRID`` (a delay shifts the GPS velocity by about D x the interval's mean
  acceleration). None unless it narrows that spread by ``MIN_GAIN`` (a flight without
  manoeuvres tells nothing).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = ["fix_epochs", "latency", "week_seconds"]

WEEK_S = 604800.0
MIN_FIXES = 20             # fixes with a time of week needed to fit the epochs
PAIR_S = 30.0              # s of time of week between the fixes whose slopes make the fit's slope
LOW_QUANTILE = 0.02        # the lag behind the fitted line taken as the epochs' offset
MAX_SHIFT_S = 0.5          # s, the most a fix may move from its stamp
NO_JITTER_S = 1e-3         # s, stamps closer than this to their epochs are kept as they are
MAX_SLOPE_ERR = 0.15       # the two clocks' rates may differ by this fraction at most
LATENCY_GRID = np.round(np.arange(0.0, 0.301, 0.02), 2)   # s
MIN_GAIN = 0.05            # the least fractional narrowing of the spread a latency must bring


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
    if near.sum() < MIN_FIXES or np.any(np.diff(new[keep]) <= 0):
        return t, every, None
    dev = lag[near[ok]] - offset
    jitter = float(np.std(dev - np.median(dev)))
    rate = f"; the autopilot's clock runs {abs(slope - 1) * 100:.1f}% {'slow' if slope < 1 else 'fast'} " \
           "against GPS time" if abs(slope - 1.0) > 2e-3 else ""
    late = int(ok.sum() - near.sum())
    again = int((~keep).sum())
    if jitter < NO_JITTER_S and abs(slope - 1.0) <= 2e-3 and not late:     # stamped at the epochs already
        return t, keep, (f"gps: {again} fixes read twice (the same time of week) dropped" if again else None)
    return new, keep, (f"gps: {int(near.sum())} fixes stamped at the receiver's epochs (GPS time of week), "
                 f"the logged stamps' jitter {jitter * 1e3:.0f} ms std removed{rate}"
                 + (f"; {late} read more than {MAX_SHIFT_S:g} s after their epoch keep their stamps" if late else "")
                 + (f"; {again} fixes read twice (the same time of week) dropped" if again else ""))


def latency(rows: pd.DataFrame) -> float | None:
    """The receiver's latency (s) estimated from one flight's replay rows fused without one
    (columns t, gps_vel_x/y, res_gps_r_vx/vy, est_vel_x/y, optionally in_air; see the module
    text); None where the rows cannot tell."""
    need = ("t", "gps_vel_x", "gps_vel_y", "res_gps_r_vx", "res_gps_r_vy", "est_vel_x", "est_vel_y")
    if any(c not in rows.columns for c in need) or len(rows) < 3 * MIN_FIXES:
        return None
    t = rows["t"].to_numpy(dtype=float)
    gv = rows[["gps_vel_x", "gps_vel_y"]].to_numpy(dtype=float)
    pred = gv - rows[["res_gps_r_vx", "res_gps_r_vy"]].to_numpy(dtype=float)
    post = rows[["est_vel_x", "est_vel_y"]].to_numpy(dtype=float)
    dt = np.diff(t)
    imu_dv = pred[1:] - post[:-1]                  # the filter's propagation over each interval
    gps_dv = np.diff(gv, axis=0)
    acc = imu_dv / np.where(dt > 0, dt, np.nan)[:, None]
    use = np.isfinite(imu_dv).all(axis=1) & np.isfinite(gps_dv).all(axis=1) & (dt > 0)
    if "in_air" in rows.columns:
        air = rows["in_air"].to_numpy(dtype=float) > 0.5
        use &= air[1:] & air[:-1]
    # the change of the interval's acceleration, what a delay D adds D times to the difference
    dacc = np.vstack([np.zeros((1, 2)), np.diff(acc, axis=0)])
    use &= np.isfinite(dacc).all(axis=1)
    if use.sum() < 3 * MIN_FIXES:
        return None
    e, da = (gps_dv - imu_dv)[use], dacc[use]

    def spread(d: float) -> float:
        x = e + d * da
        return float(np.mean(np.median(np.abs(x - np.median(x, axis=0)), axis=0)))

    s = np.array([spread(d) for d in LATENCY_GRID])
    best = int(np.argmin(s))
    if best == 0 or s[best] > (1.0 - MIN_GAIN) * s[0]:
        return None
    return float(LATENCY_GRID[best])
